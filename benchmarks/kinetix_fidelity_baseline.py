"""Kinetix's own outcomes of simple policies on level files, run inside a separate virtualenv holding kinetix-env
(see benchmarks/fidelity.py, which starts it and compares with ours).

Jobs, each printing JSON documents on stdout, one a line:
- `--sample SIZE:COUNT:SEED ...`: sample COUNT levels of SIZE with Kinetix's own level sampler (key SEED) and write
  each as a Kinetix level JSON file `<--sample-dir>/<SIZE>/k<SEED>-<index>.json`, so both engines play the very same
  levels (level i is the same whatever COUNT: the sampler's keys are a prefix-stable split of SEED);
- `--levels FILE ...`: play each level file under the no-op policy (one episode: it is deterministic) and the uniform
  random multi-discrete policy (`--episodes` episodes), up to one episode's length from the level's start, and count
  how the first episode ends: success (green touches blue), failure (green touches red), timeout, unstable (NaN).
  Levels of a size run `--chunk-levels` at a time, both policies in one compiled program from a work queue, so
  finished episodes cost no steps (random hand-designed s levels: 61 % of the steps of full-length episodes); each
  chunk's outcomes are printed as soon as it is played, so a caller keeps them if the run stops later. A level's
  random actions derive from the seed and the level file's bytes alone (`level_id`), so its outcomes do not depend
  on which other levels are played with it;
- `--variant KEY=VALUE ...` (with `--levels`): play Kinetix changed in one respect (`kinetix_variants.VARIANTS`),
  to measure how far Kinetix's own rates move under a change that any other engine makes too: the agreement that a
  faithful engine other than Jax2D itself could reach;
- `--trace LEVEL --actions FILE --trace-out FILE`: play fixed multi-discrete action sequences (episodes, steps, 6)
  from the level's start without reset and write every shape's pose and velocity and the reward and done flag after
  each env step to an .npz file (benchmarks/fidelity_trace.py pairs them with kforge's);
- `--trace LEVEL --actions FILE --state-at STEP --state-out FILE`: play the first sequence's first STEP actions and
  write the state reached as a Kinetix level file (so both engines can go on from the very same state).

Not importable from the project's environment.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from kinetix.environment import (
    ActionType,
    EnvParams,
    ObservationType,
    make_kinetix_env,
    static_env_params_from_size,
)
from kinetix.environment.ued.ued import make_reset_fn_sample_kinetix_level
from kinetix.util.saving import expand_env_state, export_env_state_to_json, load_from_json_file

from benchmarks.kinetix_variants import parse_variant

MULTI_DISCRETE_SIZES = (3, 3, 3, 3, 2, 2)
OUTCOMES = ("timeout", "success", "failure", "unstable")
"""Outcome names by code; the order of `env.rollout.Outcome` in kforge."""
QUEUE_SLOTS = 512
"""Episodes stepped together; Kinetix's env steps per second stop growing from about 256 on a CPU."""
CALL_ROUNDING = 64
"""Fewer episodes than slots take a multiple of this many slots."""
CHUNK_LEVELS = 64
"""Levels played per compiled call, and between two printed results, by default."""


PARAMS_FIELDS = {"baumgarte_collision": "baumgarte_coefficient_collision", "slop": "slop"}
STATIC_FIELDS = {"solver_iterations": "num_solver_iterations", "solver_batch_size": "solver_batch_size"}
"""The field of Kinetix's EnvParams or StaticEnvParams that each variant sets (padding_writes patches Jax2D;
substeps divides the physics step and multiplies the frame skip)."""


def variant_env_params(size: str, variant: dict):
    """Kinetix's EnvParams (no dense reward) and StaticEnvParams of `size`, changed by `variant` (its padding writes
    aside, which `drop_padding_writes` patches)."""
    static, params = static_env_params_from_size(size), EnvParams(dense_reward_scale=0.0)
    params = params.replace(**{PARAMS_FIELDS[k]: v for k, v in variant.items() if k in PARAMS_FIELDS})
    static = static.replace(**{STATIC_FIELDS[k]: v for k, v in variant.items() if k in STATIC_FIELDS})
    substeps = variant.get("substeps", 1)
    return params.replace(dt=params.dt / substeps), static.replace(frame_skip=static.frame_skip * substeps)


DISC_INERTIA_OF_JAX2D = 0.25
"""Jax2D's moment of inertia of a disc [m r^2] (its bug B2)."""
UNIFORM_DISC_INERTIA = 0.5
"""A uniform disc's moment of inertia [m r^2]."""


def with_exact_disc_inertia(state):
    """`state` with every disc's inverse moment of inertia that of a uniform disc, 1 / (m r^2 / 2), in place of
    Jax2D's 1 / (m r^2 / 4); static discs (inverse 0) stay static."""
    inverse_inertia = state.circle.inverse_inertia * DISC_INERTIA_OF_JAX2D / UNIFORM_DISC_INERTIA
    return state.replace(circle=state.circle.replace(inverse_inertia=inverse_inertia))


def drop_padding_writes() -> None:
    """Patch the installed Jax2D so that its contact solver's padding rows (index -1) write nothing: the impulses
    they reset otherwise land on the last pair of each kind (B1). Engines built afterwards use the patched solver;
    the arithmetic of every real pair is unchanged."""
    import inspect

    import jax2d.engine

    source = inspect.getsource(jax2d.engine.make_impulse_resolver_fn)
    kept = "jnp.where(indexes < 0, n_manifolds_to_compute, indexes)"
    patched = source
    for row in ("acc_impulse_normal", "acc_impulse_tangent"):
        for target in (f"{row}.at[indexes, secondary_index]", f"{row}.at[indexes]"):
            value = "iN" if row == "acc_impulse_normal" else "iT"
            old = f"{target}.set({value})"
            new = f'{target.replace("[indexes", "[" + kept)}.set({value}, mode="drop")'
            if old not in patched:
                raise SystemExit(f"jax2d's make_impulse_resolver_fn has no {old!r}: another jax2d version?")
            patched = patched.replace(old, new)
    namespace = dict(vars(jax2d.engine))
    exec(compile(patched, jax2d.engine.__file__, "exec"), namespace)
    jax2d.engine.make_impulse_resolver_fn = namespace["make_impulse_resolver_fn"]


def log(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def sample_levels(size: str, count: int, seed: int, out_dir: Path) -> list[str]:
    static, params = static_env_params_from_size(size), EnvParams()
    sample = jax.jit(jax.vmap(make_reset_fn_sample_kinetix_level(params, static)))
    states = sample(jax.random.split(jax.random.key(seed), count))
    folder = out_dir / size
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for index in range(count):
        path = folder / f"k{seed}-{index:05d}.json"
        export_env_state_to_json(str(path), jax.tree.map(lambda x, i=index: x[i], states), static, params)
        paths.append(str(path))
    return paths


def size_of(static) -> str:
    """The Kinetix size whose entity counts a level file's static parameters have."""
    counts = ("num_polygons", "num_circles", "num_joints", "num_thrusters")
    for size in ("s", "m", "l"):
        reference = static_env_params_from_size(size)
        if all(getattr(static, name) == getattr(reference, name) for name in counts):
            return size
    raise ValueError(f"level sizes {static} match no Kinetix size")


def level_id(path: str) -> int:
    """A level's 31-bit identity from its file's bytes: the key of its random actions (benchmarks/fidelity.py keys
    its stored outcomes by the same bytes)."""
    return int.from_bytes(hashlib.sha256(Path(path).read_bytes()).digest()[:4], "little") >> 1


def play(paths: list[str], episodes: int, seed: int, chunk_levels: int, emit, variant: dict | None = None) -> None:
    """Per level file, outcome counts of the first episode under the no-op and the uniform random policy; `emit`
    receives them `chunk_levels` levels at a time, as each chunk is played; `variant` changes Kinetix
    (`kinetix_variants`)."""
    variant = variant or {}
    if variant.get("padding_writes") == 0:
        drop_padding_writes()
    groups: dict[str, list[tuple[str, object]]] = {}
    for path in paths:
        state, static, _ = load_from_json_file(str(Path(path).resolve()))
        size = size_of(static)
        state = expand_env_state(state, static_env_params_from_size(size))
        if variant.get("exact_disc_inertia") == 1:
            state = with_exact_disc_inertia(state)
        groups.setdefault(size, []).append((path, state))
    for size, members in groups.items():
        params, static = variant_env_params(size, variant)
        env = make_kinetix_env(
            ActionType.MULTI_DISCRETE, ObservationType.SYMBOLIC_FLAT, None, params, static, auto_reset=False
        )
        chunk = min(chunk_levels, len(members))
        for first in range(0, len(members), chunk):
            played = members[first : first + chunk]
            padded = played + [played[-1]] * (chunk - len(played))  # one program for every chunk of the size
            levels = jax.tree.map(lambda *xs: jnp.stack(xs), *(state for _, state in padded))
            ids = jnp.asarray([level_id(path) for path, _ in padded], jnp.uint32)
            started = time.perf_counter()
            codes, steps = _queue_outcomes(env, params, levels, ids, episodes, jax.random.key(seed))
            log(
                f"kinetix {size}: levels {first + 1}-{first + len(played)} of {len(members)} x {episodes} episodes "
                f"in {time.perf_counter() - started:.0f} s ({steps} env steps, "
                f"{steps / (chunk * (episodes + 1) * int(params.max_timesteps)):.0%} of full-length episodes)"
            )
            emit(
                {
                    path: {
                        "size": size,
                        "noop": OUTCOMES[int(codes[index, 0])],
                        "random": {name: int((codes[index, 1:] == code).sum()) for code, name in enumerate(OUTCOMES)},
                    }
                    for index, (path, _) in enumerate(played)
                }
            )


def _queue_outcomes(env, params, levels, ids, episodes: int, key) -> tuple[np.ndarray, int]:
    """(levels, 1 + episodes) first-episode outcome codes (column 0: the no-op; then random actions) and the env
    steps taken. Episodes run from a work queue in QUEUE_SLOTS slots: a slot whose episode ended takes the next
    episode, so no step is spent on finished episodes and one compiled program plays every level of a chunk."""
    num_levels = jax.tree.leaves(levels)[0].shape[0]
    per_level = episodes + 1
    total = num_levels * per_level
    slots = min(QUEUE_SLOTS, -(-total // CALL_ROUNDING) * CALL_ROUNDING)
    codes, steps = _compiled_queue(env, params, per_level, total, slots)(levels, ids, key)
    return np.asarray(codes).reshape(num_levels, per_level), int(steps)


_COMPILED = {}


def _compiled_queue(env, params, per_level: int, total: int, slots: int):
    """jit(levels, level ids, key) -> (outcome code per episode, env steps taken); episode e plays level
    l = e // per_level, with the no-op when e % per_level == 0, else uniform random actions from key (id of l,
    e % per_level, timestep)."""
    cache_key = (id(env), per_level, total, slots)
    if cache_key not in _COMPILED:
        sizes = jnp.asarray(MULTI_DISCRETE_SIZES)

        def start_of(levels, episode):
            level = jnp.clip(episode, 0, total - 1) // per_level
            return jax.tree.map(lambda x: x[level], levels)

        def actions_of(key, ids, episode, timestep):
            level_key = jax.random.fold_in(key, ids[jnp.clip(episode, 0, total - 1) // per_level])
            action_key = jax.random.fold_in(jax.random.fold_in(level_key, episode % per_level), timestep)
            random = jax.random.randint(action_key, (len(MULTI_DISCRETE_SIZES),), 0, sizes)
            return jnp.where(episode % per_level == 0, 0, random)

        def run(levels, ids, key):
            def body(carry):
                states, episode, next_episode, codes, steps = carry
                actions = jax.vmap(actions_of, (None, None, 0, 0))(key, ids, episode, states.timestep)
                keys = jax.random.split(jax.random.fold_in(key, steps), slots)
                _, stepped, reward, done, _ = jax.vmap(env.step, (0, 0, 0, None))(keys, states, actions, params)
                unstable = jax.vmap(_has_nan)(stepped)
                code = jnp.where(unstable, 3, jnp.where(reward > 0, 1, jnp.where(reward < 0, 2, 0)))
                playing = episode < total
                ended = done & playing
                codes = codes.at[jnp.where(ended, episode, total)].set(code, mode="drop")
                new_episode = next_episode + jnp.cumsum(ended) - 1
                episode = jnp.where(ended, jnp.where(new_episode < total, new_episode, total), episode)
                fresh = jax.vmap(start_of, (None, 0))(levels, episode)
                states = jax.tree.map(
                    lambda f, s: jnp.where(ended.reshape((-1,) + (1,) * (f.ndim - 1)), f, s), fresh, stepped
                )
                return states, episode, next_episode + ended.sum(), codes, steps + playing.sum()

            episode = jnp.arange(slots)
            start = (
                jax.vmap(start_of, (None, 0))(levels, episode),
                jnp.where(episode < total, episode, total),
                jnp.asarray(slots),
                jnp.zeros(total, jnp.int32),
                jnp.asarray(0),
            )
            _, _, _, codes, steps = jax.lax.while_loop(lambda carry: (carry[1] < total).any(), body, start)
            return codes, steps

        _COMPILED[cache_key] = jax.jit(run)
    return _COMPILED[cache_key]


TRACE_FIELDS = {
    "polygon_position": lambda s: s.polygon.position,
    "polygon_rotation": lambda s: s.polygon.rotation,
    "polygon_velocity": lambda s: s.polygon.velocity,
    "polygon_angular_velocity": lambda s: s.polygon.angular_velocity,
    "circle_position": lambda s: s.circle.position,
    "circle_rotation": lambda s: s.circle.rotation,
    "circle_velocity": lambda s: s.circle.velocity,
    "circle_angular_velocity": lambda s: s.circle.angular_velocity,
}
"""What a trace records of Kinetix's state after each env step."""


def _level_without_reset(path: str):
    """(start state, env without auto-reset, static params, env params) of a level file, in its size's shapes."""
    state, static, _ = load_from_json_file(str(Path(path).resolve()))
    static, params = static_env_params_from_size(size_of(static)), EnvParams(dense_reward_scale=0.0)
    env = make_kinetix_env(
        ActionType.MULTI_DISCRETE, ObservationType.SYMBOLIC_FLAT, None, params, static, auto_reset=False
    )
    return expand_env_state(state, static), env, static, params


def trace(path: str, actions: np.ndarray, out: Path) -> None:
    """Every episode of `actions` (episodes, steps, 6) played from the level's start; poses etc. per step to `out`."""
    state, env, _, params = _level_without_reset(path)

    def episode(episode_actions):
        def body(current, action):
            _, stepped, reward, done, _ = env.step(jax.random.key(0), current, action, params)
            return stepped, ({name: get(stepped) for name, get in TRACE_FIELDS.items()}, reward, done)

        return jax.lax.scan(body, state, episode_actions)[1]

    fields, reward, done = jax.jit(jax.vmap(episode))(jnp.asarray(actions))
    np.savez(out, reward=np.asarray(reward), done=np.asarray(done), **{k: np.asarray(v) for k, v in fields.items()})


def export_state_at(path: str, actions: np.ndarray, steps: int, out: Path) -> None:
    """The state after the first `steps` actions of `actions[0]`, played from the level's start, as a level file."""
    state, env, static, params = _level_without_reset(path)

    def body(current, action):
        return env.step(jax.random.key(0), current, action, params)[1], None

    reached = jax.jit(lambda s, a: jax.lax.scan(body, s, a)[0])(state, jnp.asarray(actions[0, :steps]))
    export_env_state_to_json(str(out), reached, static, params)


def _has_nan(state) -> jnp.ndarray:
    return jax.tree.reduce(jnp.logical_or, jax.tree.map(lambda x: jnp.isnan(x).any(), state), False)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sample", nargs="*", default=[], help="SIZE:COUNT:SEED, levels to sample and write")
    parser.add_argument("--sample-dir", type=Path, help="folder that receives the sampled level files")
    parser.add_argument("--levels", nargs="*", default=[], help="level JSON files to play")
    parser.add_argument("--levels-from", type=Path, help="a text file listing level JSON files to play, one a line")
    parser.add_argument("--episodes", type=int, default=256, help="random-policy episodes per level")
    parser.add_argument("--seed", type=int, default=0, help="seed of the random policy's actions")
    parser.add_argument("--trace", help="a level JSON file to play with --actions, recorded to --trace-out")
    parser.add_argument("--actions", type=Path, help=".npy of multi-discrete actions (episodes, steps, 6)")
    parser.add_argument("--trace-out", type=Path, help=".npz that receives the trace")
    parser.add_argument("--state-at", type=int, help="with --trace: env steps of the first sequence to play")
    parser.add_argument("--state-out", type=Path, help="level file that receives the state after --state-at steps")
    parser.add_argument("--chunk-levels", type=int, default=CHUNK_LEVELS, help="levels played per printed result")
    parser.add_argument(
        "--variant",
        type=parse_variant,
        action="append",
        default=[],
        help="KEY=VALUE: Kinetix changed (kinetix_variants.py)",
    )
    args = parser.parse_args(argv)

    def emit(document: dict) -> None:
        print(json.dumps(document), flush=True)

    if args.trace and args.state_at is not None:
        export_state_at(args.trace, np.load(args.actions), args.state_at, args.state_out)
    elif args.trace:
        trace(args.trace, np.load(args.actions), args.trace_out)
    for spec in args.sample:
        size, count, seed = spec.split(":")
        emit({"sampled": {spec: sample_levels(size, int(count), int(seed), args.sample_dir)}})
    paths = list(args.levels)
    if args.levels_from is not None:
        paths += [line for line in args.levels_from.read_text().splitlines() if line]
    if paths:
        play(
            paths,
            args.episodes,
            args.seed,
            args.chunk_levels,
            lambda played: emit({"played": played}),
            dict(args.variant),
        )


if __name__ == "__main__":
    main()
