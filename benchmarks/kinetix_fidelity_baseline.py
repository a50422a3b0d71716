"""Kinetix's own outcomes of simple policies on level files, run inside a separate virtualenv holding kinetix-env
(see benchmarks/fidelity.py, which starts it and compares with ours).

Two jobs, one JSON document on stdout:
- `--sample SIZE:COUNT:SEED ...`: sample COUNT levels of SIZE with Kinetix's own level sampler (key SEED) and write
  each as a Kinetix level JSON file `<--sample-dir>/<SIZE>/k<SEED>-<index>.json`, so both engines play the very same
  levels;
- `--levels FILE ...`: play each level file under the no-op policy (one episode: it is deterministic) and the uniform
  random multi-discrete policy (`--episodes` episodes), up to one episode's length from the level's start, and count
  how the first episode ends: success (green touches blue), failure (green touches red), timeout, unstable (NaN).

Not importable from the project's environment.
"""

from __future__ import annotations

import argparse
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

MULTI_DISCRETE_SIZES = (3, 3, 3, 3, 2, 2)
OUTCOMES = ("timeout", "success", "failure", "unstable")
"""Outcome names by code; the order of `env.Outcome` in kforge."""
EPISODES_PER_CALL = 4096
"""Most episodes stepped together in one compiled call (levels x episodes are cut into calls of this size)."""
CALL_ROUNDING = 64
"""A smaller call is padded to a multiple of this many episodes."""


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


def _size_of(static) -> str:
    for size in ("s", "m", "l"):
        reference = static_env_params_from_size(size)
        if (static.num_polygons, static.num_circles, static.num_joints, static.num_thrusters) == (
            reference.num_polygons,
            reference.num_circles,
            reference.num_joints,
            reference.num_thrusters,
        ):
            return size
    raise ValueError(f"level sizes {static} match no Kinetix size")


def play(paths: list[str], episodes: int, seed: int) -> dict:
    """Per level file: outcome counts of the first episode under the no-op and the uniform random policy."""
    groups: dict[str, list[tuple[str, object]]] = {}
    for path in paths:
        state, static, _ = load_from_json_file(str(Path(path).resolve()))
        size = _size_of(static)
        groups.setdefault(size, []).append((path, expand_env_state(state, static_env_params_from_size(size))))
    report = {}
    for size, members in groups.items():
        static, params = static_env_params_from_size(size), EnvParams(dense_reward_scale=0.0)
        env = make_kinetix_env(
            ActionType.MULTI_DISCRETE, ObservationType.SYMBOLIC_FLAT, None, params, static, auto_reset=False
        )
        levels = jax.tree.map(lambda *xs: jnp.stack(xs), *(state for _, state in members))
        started = time.perf_counter()
        noop = _outcomes(env, params, levels, 1, None)
        random = _outcomes(env, params, levels, episodes, jax.random.key(seed))
        log(f"kinetix {size}: {len(members)} levels x {episodes} episodes in {time.perf_counter() - started:.0f} s")
        for index, (path, _) in enumerate(members):
            report[path] = {
                "size": size,
                "noop": OUTCOMES[int(noop[index, 0])],
                "random": {name: int((random[index] == code).sum()) for code, name in enumerate(OUTCOMES)},
            }
    return report


def _outcomes(env, params, levels, episodes: int, key) -> np.ndarray:
    """(levels, episodes) outcome codes of the first episode; random actions when `key` is given, else no-op."""
    num_levels = jax.tree.leaves(levels)[0].shape[0]
    level_index = np.repeat(np.arange(num_levels), episodes)
    call = min(EPISODES_PER_CALL, -(-len(level_index) // CALL_ROUNDING) * CALL_ROUNDING)
    codes = []
    for start in range(0, len(level_index), call):
        chunk = level_index[start : start + call]
        padded = np.concatenate([chunk, np.full(call - len(chunk), chunk[-1])])
        batch = jax.tree.map(lambda x, rows=padded: x[rows], levels)
        call_key = jax.random.fold_in(key, start) if key is not None else jax.random.key(0)
        codes.append(np.asarray(_rollout(env, params, batch, call_key, key is not None))[: len(chunk)])
    return np.concatenate(codes).reshape(num_levels, episodes)


def _rollout(env, params, states, key, random: bool):
    return _compiled_rollout(env, params, random)(states, key)


_COMPILED = {}


def _compiled_rollout(env, params, random: bool):
    """jit(states, key) -> first-episode outcome codes, one compile per env and policy."""
    cache_key = (id(env), random)  # one jit per env and policy; it retraces for each call size
    if cache_key not in _COMPILED:
        sizes = jnp.asarray(MULTI_DISCRETE_SIZES)
        num_steps = int(params.max_timesteps)

        def rollout(states, key):
            batch = jax.tree.leaves(states)[0].shape[0]

            def body(carry, t):
                states, outcome, done = carry
                step_key = jax.random.fold_in(key, t)
                if random:
                    actions = jax.random.randint(step_key, (batch, len(sizes)), 0, sizes)
                else:
                    actions = jnp.zeros((batch, len(sizes)), jnp.int32)
                keys = jax.random.split(step_key, batch)
                _, new_states, reward, now_done, _ = jax.vmap(env.step, (0, 0, 0, None))(keys, states, actions, params)
                unstable = jax.vmap(_has_nan)(new_states)
                this = jnp.where(unstable, 3, jnp.where(reward > 0, 1, jnp.where(reward < 0, 2, 0)))
                ended = now_done & ~done
                outcome = jnp.where(ended, this, outcome)
                return (new_states, outcome, done | now_done), None

            start = (states, jnp.zeros(batch, jnp.int32), jnp.zeros(batch, bool))
            (_, outcome, _), _ = jax.lax.scan(body, start, jnp.arange(num_steps))
            return outcome

        _COMPILED[cache_key] = jax.jit(rollout)
    return _COMPILED[cache_key]


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
    args = parser.parse_args(argv)
    report = {"sampled": {}, "played": {}}
    for spec in args.sample:
        size, count, seed = spec.split(":")
        report["sampled"][spec] = sample_levels(size, int(count), int(seed), args.sample_dir)
    paths = list(args.levels)
    if args.levels_from is not None:
        paths += [line for line in args.levels_from.read_text().splitlines() if line]
    if paths:
        report["played"] = play(paths, args.episodes, args.seed)
    json.dump(report, sys.stdout)


if __name__ == "__main__":
    main()
