"""One level, step by step in both engines: the same action sequences played in kforge and in kinetix-env.

Where `benchmarks/fidelity.py` finds that a level's outcome rates disagree, this finds where the engines part: it
draws `--episodes` uniform random multi-discrete action sequences once (or the no-op with `--noop`), plays each from
the level's start in both engines without reset, and prints how the paired episodes ended (a table of kforge's
outcome against Kinetix's) and, for each episode that ended differently, both ends and the first env step at which
some shape's position differs by more than `--tolerance`. `--save FILE` keeps both traces (every shape's pose and
velocity after each env step, in Kinetix's slot order) for a closer look.

`--from-step EPISODE:STEP` starts both engines from the very same state, Kinetix's after STEP env steps of that
paired episode (written as a level file), and plays the episode on from there: the first step's table of every
movable shape's position and velocity in both engines shows what one step does differently, free of the small
differences that grew before it (contact and joint impulses kept for warm starting are Kinetix's own, ours start
from none).

    python -m benchmarks.fidelity_trace l/mjc_half_cheetah --episodes 64
    python -m benchmarks.fidelity_trace levels/s/k0-00002.json --noop --sim speculative_reach=0
    python -m benchmarks.fidelity_trace levels/s/k0-00030.json --noop --substeps 1 --iterations 10 --relax-iterations 0
    python -m benchmarks.fidelity_trace levels/s/k0-00454.json --noop --from-step 0:21 --substeps 1 --iterations 10 \
        --relax-iterations 0 --sim contact_law=1 --sim force_timing=1 --sim speculative_distance=0 \
        --sim speculative_reach=0 --sim contact_points=1

(the second a random level that `python -m benchmarks.fidelity --random-levels 64 --level-dir levels` sampled.)
"""

from __future__ import annotations

import argparse
import dataclasses
import subprocess
import tempfile
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks.kinetix_venv import DEFAULT_KINETIX_VENV, REPOSITORY, baseline_command, kinetix_python
from benchmarks.sim_overrides import (
    add_physics_option,
    add_solver_scheme_options,
    sim_override,
    solver_scheme,
    with_sim_overrides,
    with_solver_scheme,
)
from kforge.engine import physics_scheme
from kforge.engine.schemes import DEFAULT_PHYSICS_SCHEME
from kforge.env import (
    MULTI_DISCRETE_SIZES,
    ActionType,
    EnvParams,
    advance,
    bundled_level_path,
    load_level,
    reset,
    state_to_kinetix,
    under_scheme,
)

KINETIX_BASELINE = "kinetix_fidelity_baseline"
OUTCOMES = ("timeout", "success", "failure")
EPISODE_STEPS = 256
"""Env steps of one episode (Kinetix's max_timesteps)."""
TRACED = {
    "polygon_position": "polygon/position",
    "polygon_rotation": "polygon/rotation",
    "polygon_velocity": "polygon/velocity",
    "polygon_angular_velocity": "polygon/angular_velocity",
    "circle_position": "circle/position",
    "circle_rotation": "circle/rotation",
    "circle_velocity": "circle/velocity",
    "circle_angular_velocity": "circle/angular_velocity",
}
"""Trace field -> kforge's state leaf in Kinetix's naming (`env.state_to_kinetix`)."""


def level_path(name: str) -> Path:
    """A bundled level's name (`s/h1_thrust_over_ball`) or a level file's path, made absolute (Kinetix's side runs
    from the top of the checkout)."""
    path = Path(name)
    return path.absolute() if path.suffix == ".json" else bundled_level_path(name)


def random_actions(episodes: int, seed: int) -> np.ndarray:
    """(episodes, EPISODE_STEPS, 6) uniform multi-discrete actions."""
    rng = np.random.default_rng(seed)
    columns = [rng.integers(0, size, (episodes, EPISODE_STEPS)) for size in MULTI_DISCRETE_SIZES]
    return np.stack(columns, -1).astype(np.int32)


def trace_ours(
    loaded, actions: np.ndarray, sim_overrides: dict, scheme: dict | None = None, physics: str = DEFAULT_PHYSICS_SCHEME
) -> dict:
    """kforge's trace of `actions` on a loaded level (`env.LoadedLevel`) under the named `physics` scheme, then with
    the solver scheme's settings in `scheme` if given (`benchmarks.sim_overrides.with_solver_scheme`) and
    `sim_overrides`: TRACED fields, reward sign and done per env step."""
    params, static = under_scheme(physics_scheme(physics), EnvParams(dense_reward_scale=0.0), loaded.static)
    sim, static_sim = with_sim_overrides(params.sim, static.sim, sim_overrides)
    params = params.replace(sim=sim)
    static = dataclasses.replace(static, sim=with_solver_scheme(static_sim, scheme or {}))

    def episode(episode_actions):
        def body(state, action):
            stepped, result = advance(state, action, params, static, ActionType.MULTI_DISCRETE)
            reward = jnp.where(result.success, 1.0, jnp.where(result.failure, -1.0, 0.0))
            return stepped, (stepped, reward, result.done)

        return jax.lax.scan(body, reset(loaded.level), episode_actions)[1]

    states, reward, done = jax.jit(jax.vmap(episode))(jnp.asarray(actions))
    leaves = state_to_kinetix(states, loaded.static)
    return {field: leaves[leaf] for field, leaf in TRACED.items()} | {
        "reward": np.asarray(reward),
        "done": np.asarray(done),
    }


def trace_kinetix(python: Path, path: Path, actions: np.ndarray, folder: Path) -> dict:
    actions_file, out = folder / "actions.npy", folder / "kinetix_trace.npz"
    np.save(actions_file, actions)
    command = baseline_command(python, KINETIX_BASELINE, "--trace", str(path), "--actions", str(actions_file))
    result = subprocess.run([*command, "--trace-out", str(out)], capture_output=True, text=True, cwd=REPOSITORY)
    if result.returncode != 0:
        raise RuntimeError(f"Kinetix's side failed:\n{result.stderr[-3000:]}")
    return dict(np.load(out))


def episode_ends(trace: dict) -> tuple[np.ndarray, np.ndarray]:
    """Per episode: the env step its first episode ended at (the trace's length if never) and the outcome index."""
    done = np.asarray(trace["done"], bool)
    length = done.shape[1]
    step = np.where(done.any(1), done.argmax(1), length)
    reward = np.take_along_axis(trace["reward"], np.minimum(step, length - 1)[:, None], 1)[:, 0]
    outcome = np.where(step == length, 0, np.where(reward > 0, 1, np.where(reward < 0, 2, 0)))
    return step, outcome


def parse_from_step(text: str) -> tuple[int, int]:
    """'EPISODE:STEP' -> (episode, step), both >= 0 and STEP below an episode's length."""
    try:
        episode, step = (int(part) for part in text.split(":"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected EPISODE:STEP (two integers), got {text!r}") from None
    if episode < 0 or not 0 <= step < EPISODE_STEPS:
        raise argparse.ArgumentTypeError(f"EPISODE must be >= 0 and STEP in [0, {EPISODE_STEPS}), got {text!r}")
    return episode, step


def kinetix_state_at(python: Path, path: Path, actions: np.ndarray, steps: int, folder: Path) -> Path:
    """Kinetix's state after the first `steps` actions of `actions[0]` from the level's start, as a level file."""
    actions_file, out = folder / "actions_to_state.npy", folder / "kinetix_state.json"
    np.save(actions_file, actions)
    command = baseline_command(python, KINETIX_BASELINE, "--trace", str(path), "--actions", str(actions_file))
    result = subprocess.run(
        [*command, "--state-at", str(steps), "--state-out", str(out)],
        capture_output=True,
        text=True,
        cwd=REPOSITORY,
    )
    if result.returncode != 0:
        raise RuntimeError(f"Kinetix's side failed:\n{result.stderr[-3000:]}")
    return out


def first_step_table(ours: dict, theirs: dict, active_polygons, active_circles, movable) -> list[str]:
    """One line per active movable shape: its position, velocity and spin after the first traced step in both
    engines."""
    lines = [
        f"{'shape':8s} {'kforge position':>18s} {'Kinetix position':>18s} {'kforge velocity':>18s} "
        f"{'Kinetix velocity':>18s} {'kforge spin':>11s} {'Kinetix spin':>12s}"
    ]
    for kind, active in (("polygon", active_polygons), ("circle", active_circles)):
        for index in np.flatnonzero(active & movable[kind]):
            row = [f"{kind[0]}{index}"]
            for field in ("position", "velocity"):
                for trace in (ours, theirs):
                    x, y = trace[f"{kind}_{field}"][0, 0, index]
                    row.append(f"({x:7.3f}, {y:7.3f})")
            row += [f"{trace[f'{kind}_angular_velocity'][0, 0, index]:11.3f}" for trace in (ours, theirs)]
            lines.append(f"{row[0]:8s} " + " ".join(f"{cell:>18s}" for cell in row[1:5]) + " " + " ".join(row[5:]))
    return lines


def first_divergence(ours: dict, theirs: dict, active_polygons, active_circles, tolerance: float) -> np.ndarray:
    """Per episode: the first env step after which some active shape is more than `tolerance` apart; -1 if none."""
    gaps = [np.abs(ours["polygon_position"] - theirs["polygon_position"]).max(-1)[..., active_polygons]]
    if active_circles.any():
        gaps.append(np.abs(ours["circle_position"] - theirs["circle_position"]).max(-1)[..., active_circles])
    apart = np.concatenate(gaps, -1).max(-1) > tolerance
    return np.where(apart.any(1), apart.argmax(1), -1)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("level", help="a bundled level (s/h1_thrust_over_ball) or a level JSON file")
    parser.add_argument("--episodes", type=int, default=64, help="paired random-action episodes")
    parser.add_argument("--noop", action="store_true", help="play the no-op policy (one episode) instead")
    parser.add_argument("--seed", type=int, default=0, help="seed of the random actions")
    add_physics_option(parser)
    parser.add_argument(
        "--sim", type=sim_override, action="append", default=[], help="SimParams or law KEY=VALUE of ours"
    )
    add_solver_scheme_options(parser)
    parser.add_argument("--tolerance", type=float, default=0.01, help="[m] positions closer than this agree")
    parser.add_argument("--kinetix-venv", type=Path, default=DEFAULT_KINETIX_VENV)
    parser.add_argument("--save", type=Path, help=".npz that keeps both traces and the actions")
    parser.add_argument(
        "--from-step",
        type=parse_from_step,
        metavar="EPISODE:STEP",
        help="start both engines from Kinetix's state after STEP env steps of paired episode EPISODE (of the "
        "--episodes drawn with --seed, or 0 with --noop)",
    )
    args = parser.parse_args(argv)
    scheme = solver_scheme(args, parser)

    path = level_path(args.level)
    actions = np.zeros((1, EPISODE_STEPS, 6), np.int32) if args.noop else random_actions(args.episodes, args.seed)
    first_episode = 0 if args.from_step is None else args.from_step[0]
    if first_episode >= len(actions):
        parser.error(f"--from-step: episode {first_episode} of {len(actions)} paired episodes does not exist")
    python = kinetix_python(args.kinetix_venv, print)
    with tempfile.TemporaryDirectory(prefix="kforge-trace-") as folder:
        if args.from_step is not None:
            steps_before = args.from_step[1]
            actions = actions[first_episode : first_episode + 1]
            state = kinetix_state_at(python, path, actions, steps_before, Path(folder))
            path = Path(folder) / f"{Path(args.level).stem}-episode-{first_episode}-step-{steps_before}.json"
            state.rename(path)
            actions = actions[:, steps_before:]
        theirs = trace_kinetix(python, path, actions, Path(folder))
        loaded = load_level(path)
    ours = trace_ours(loaded, actions, dict(args.sim), scheme, args.physics)
    if args.save is not None:
        np.savez(
            args.save,
            actions=actions,
            **{f"kforge_{k}": v for k, v in ours.items()},
            **{f"kinetix_{k}": v for k, v in theirs.items()},
        )

    start = state_to_kinetix(reset(loaded.level), loaded.static)
    active_polygons, active_circles = start["polygon/active"].astype(bool), start["circle/active"].astype(bool)
    apart = first_divergence(ours, theirs, active_polygons, active_circles, args.tolerance)
    if args.from_step is not None:
        movable = {kind: np.asarray(start[f"{kind}/inverse_mass"]) > 0 for kind in ("polygon", "circle")}
        print(f"from Kinetix's state after {args.from_step[1]} env steps of episode {first_episode}, the next step:")
        print("\n".join(first_step_table(ours, theirs, active_polygons, active_circles, movable)))
    our_end, our_outcome = episode_ends(ours)
    their_end, their_outcome = episode_ends(theirs)
    table = np.zeros((3, 3), int)
    np.add.at(table, (our_outcome, their_outcome), 1)
    print(f"{path.name}: {len(actions)} paired episodes; rows kforge, columns Kinetix")
    print(f"{'':10s}" + "".join(f"{name:>10s}" for name in OUTCOMES))
    for row, name in enumerate(OUTCOMES):
        print(f"{name:10s}" + "".join(f"{count:10d}" for count in table[row]))
    offset = 0 if args.from_step is None else args.from_step[1]  # steps are counted from the level's start
    our_end, their_end = (np.minimum(offset + end, EPISODE_STEPS - 1) - offset for end in (our_end, their_end))
    for episode in np.flatnonzero((our_outcome != their_outcome) | (our_end != their_end)):
        print(
            f"episode {first_episode + episode}: kforge {OUTCOMES[our_outcome[episode]]} at step "
            f"{offset + our_end[episode]}, Kinetix {OUTCOMES[their_outcome[episode]]} at step "
            f"{offset + their_end[episode]}; apart by {args.tolerance} m from step {offset + apart[episode]}"
        )


if __name__ == "__main__":
    main()
