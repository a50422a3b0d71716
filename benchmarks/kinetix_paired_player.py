"""Kinetix's side of benchmarks/fidelity_paired.py, run inside the kinetix-env virtualenv: given action sequences
replayed from a level's start, once as the level is and once with every active shape moved by a given offset.

    python -m benchmarks.kinetix_paired_player --jobs FILE [--chunk-levels N]

FILE lists one job a line, `LEVEL_FILE INPUTS_NPZ OUT_NPZ` separated by tabs. INPUTS holds `actions` (episodes,
steps, 6) int32 and `offsets` (episodes, polygons + circles, 2) [m], the shift of each shape's start position in the
perturbed run. OUT receives per run (`plain_`, `perturbed_`): `position` (episodes, steps + 1, shapes, 2) and
`rotation` (episodes, steps + 1, shapes), polygons then circles in Kinetix's slot order with the start at step 0,
and `done` and `reward` (episodes, steps) of each env step; and `actions_sha256`, the digest of the actions' bytes
as played. Neither run resets at an episode's end: the physics plays on to the last action. Levels of a size run
`--chunk-levels` at a time in one compiled program; each job's OUT is written as its chunk ends, and a job whose OUT
exists is skipped (a run that stops resumes). Progress lines go to stderr.

Not importable from the project's environment.
"""

from __future__ import annotations

import argparse
import hashlib
import os
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
from kinetix.util.saving import expand_env_state, load_from_json_file

from benchmarks.kinetix_fidelity_baseline import log, size_of

CHUNK_LEVELS = 8
"""Levels played per compiled call by default (each with both runs of every episode)."""
RUNS = ("plain", "perturbed")


def load_level(path: str) -> tuple[str, object]:
    """(size, start state in its size's shapes) of a Kinetix level file."""
    state, static, _ = load_from_json_file(str(Path(path).resolve()))
    size = size_of(static)
    return size, expand_env_state(state, static_env_params_from_size(size))


def moved(state, offsets):
    """`state` with each active shape's position plus its row of `offsets` (polygons then circles) [m]."""
    polygons = state.polygon.position.shape[0]

    def shift(shapes, offset):
        return shapes.replace(position=shapes.position + jnp.where(shapes.active[:, None], offset, 0.0))

    return state.replace(
        polygon=shift(state.polygon, offsets[:polygons]), circle=shift(state.circle, offsets[polygons:])
    )


def pose(state) -> tuple[jnp.ndarray, jnp.ndarray]:
    """(positions (shapes, 2), rotations (shapes,)) of every shape slot, polygons then circles."""
    position = jnp.concatenate([state.polygon.position, state.circle.position])
    return position, jnp.concatenate([state.polygon.rotation, state.circle.rotation])


def compiled_player(size: str):
    """jit(levels, level index, offsets, actions) -> (position, rotation, reward, done) per episode: the episode's
    level moved by its offsets, played with its actions without reset, the start pose at step 0."""
    static, params = static_env_params_from_size(size), EnvParams(dense_reward_scale=0.0)
    env = make_kinetix_env(
        ActionType.MULTI_DISCRETE, ObservationType.SYMBOLIC_FLAT, None, params, static, auto_reset=False
    )

    def episode(levels, index, offsets, actions):
        start = moved(jax.tree.map(lambda x: x[index], levels), offsets)

        def body(state, action):
            _, stepped, reward, done, _ = env.step(jax.random.key(0), state, action, params)
            return stepped, (pose(stepped), reward, done)

        _, ((position, rotation), reward, done) = jax.lax.scan(body, start, actions)
        start_position, start_rotation = pose(start)
        position = jnp.concatenate([start_position[None], position])
        return position, jnp.concatenate([start_rotation[None], rotation]), reward, done

    return jax.jit(jax.vmap(episode, (None, 0, 0, 0)))


def play_chunk(player, jobs: list[tuple[str, object, dict]]) -> list[dict]:
    """Both runs of every job's episodes, in one call; per job, the OUT arrays."""
    levels = jax.tree.map(lambda *xs: jnp.stack(xs), *(state for _, state, _ in jobs))
    episodes, steps, _ = jobs[0][2]["actions"].shape
    index = np.repeat(np.arange(len(jobs)), 2 * episodes)
    offsets = np.concatenate([np.concatenate([np.zeros_like(i["offsets"]), i["offsets"]]) for _, _, i in jobs])
    actions = np.concatenate([np.concatenate([i["actions"], i["actions"]]) for _, _, i in jobs])
    played = [np.asarray(x) for x in player(levels, index, offsets.astype(np.float32), actions)]
    outs = []
    for number, (_, _, inputs) in enumerate(jobs):
        out = {"actions_sha256": hashlib.sha256(inputs["actions"].tobytes()).hexdigest()}
        for run_number, run in enumerate(RUNS):
            first = (2 * number + run_number) * episodes
            for name, value in zip(("position", "rotation", "reward", "done"), played, strict=True):
                out[f"{run}_{name}"] = value[first : first + episodes]
        outs.append(out)
    return outs


def write(out: Path, arrays: dict) -> None:
    """`arrays` to `out` as a whole file or not at all."""
    partial = out.with_name(out.name + ".partial.npz")
    np.savez_compressed(partial, **arrays)
    os.replace(partial, out)


def play(jobs: list[tuple[str, str, str]], chunk_levels: int) -> None:
    """Every job whose OUT is missing, levels of a size `chunk_levels` at a time (the last chunk padded)."""
    by_size: dict[str, list] = {}
    for level, inputs, out in jobs:
        if not Path(out).exists():
            size, state = load_level(level)
            by_size.setdefault(size, []).append((out, state, dict(np.load(inputs))))
    for size, members in by_size.items():
        player = compiled_player(size)
        chunk = min(chunk_levels, len(members))
        for first in range(0, len(members), chunk):
            played = members[first : first + chunk]
            started = time.perf_counter()
            outs = play_chunk(player, played + [played[-1]] * (chunk - len(played)))
            for (out, _, _), arrays in zip(played, outs, strict=False):
                write(Path(out), arrays)
            log(
                f"kinetix {size}: levels {first + 1}-{first + len(played)} of {len(members)} in "
                f"{time.perf_counter() - started:.0f} s"
            )


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--jobs", type=Path, required=True, help="LEVEL_FILE<tab>INPUTS_NPZ<tab>OUT_NPZ a line")
    parser.add_argument("--chunk-levels", type=int, default=CHUNK_LEVELS, help="levels played per compiled call")
    args = parser.parse_args(argv)
    jobs = [tuple(line.split("\t")) for line in args.jobs.read_text().splitlines() if line]
    play(jobs, args.chunk_levels)


if __name__ == "__main__":
    main()
