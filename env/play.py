"""`kforge render`: play a level file with a simple policy and write the episode as a GIF."""

from __future__ import annotations

import argparse
import functools
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from engine import DEFAULT_PHYSICS_SCHEME, PHYSICS_SCHEMES, physics_scheme
from env.actions import ActionType, noop_action, random_action
from env.episode import StepResult, reset, step
from env.gif import write_state_gif
from env.level_files import load_level
from env.params import EnvParams, StaticEnvParams, under_scheme
from env.rollout import Policy
from env.state import EnvState, Level

DEFAULT_OUT_DIR = Path("outputs")
GIF_FPS = 30.0  # [frames/s]; one frame per env step of 2/60 s plays at about real time


@functools.partial(jax.jit, static_argnames=("static", "policy", "num_steps"))
def record_episode(
    level: Level, params: EnvParams, static: StaticEnvParams, policy: Policy, key: jax.Array, num_steps: int
) -> tuple[EnvState, StepResult]:
    """States (num_steps + 1, ...) from the level's start and step results (num_steps,) under `policy`.

    Episodes that end are followed by the level's start again (auto-reset), as the dataset records them.
    """

    def body(state, step_key):
        if policy is Policy.NOOP:
            action = noop_action(ActionType.MULTI_DISCRETE)
        else:
            action = random_action(step_key, ActionType.MULTI_DISCRETE)
        next_state, result = step(state, action, level, params, static)
        return next_state, (next_state, result)

    start = reset(level)
    _, (states, results) = jax.lax.scan(body, start, jax.random.split(key, num_steps))
    states = jax.tree.map(lambda first, rest: jnp.concatenate([first[None], rest]), start, states)
    return states, results


def main(argv=None, prog: str | None = None) -> None:
    """Play LEVEL (a Kinetix level JSON file) and write a GIF of it; prints the path and how episodes ended."""
    parser = argparse.ArgumentParser(prog=prog, description=main.__doc__)
    parser.add_argument(
        "level", type=Path, help="Kinetix level JSON file (sizes s, m or l) or bundled name (s/h0_weak_thrust)"
    )
    parser.add_argument("--policy", choices=[p.value for p in Policy], default=Policy.NOOP.value)
    parser.add_argument("--steps", type=int, default=256, help="env steps to play (default 256, one episode)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the random policy")
    parser.add_argument("--out", type=Path, help="GIF path (default outputs/<level name>.gif)")
    parser.add_argument(
        "--physics",
        choices=sorted(PHYSICS_SCHEMES),
        default=DEFAULT_PHYSICS_SCHEME,
        help=f"physics scheme, as a job's env.physics (default {DEFAULT_PHYSICS_SCHEME})",
    )
    args = parser.parse_args(argv)
    if args.steps < 1:
        parser.error("--steps must be at least 1")
    loaded = load_level(args.level)
    params, static = under_scheme(physics_scheme(args.physics), loaded.params, loaded.static)
    out = args.out or DEFAULT_OUT_DIR / f"{args.level.stem}.gif"

    started = time.perf_counter()
    states, results = record_episode(
        loaded.level, params, static, Policy(args.policy), jax.random.key(args.seed), args.steps
    )
    path = write_state_gif(jax.device_get(states), static, out, fps=GIF_FPS)
    results = jax.device_get(results)
    ends = np.flatnonzero(results.done)
    outcomes = [_describe(results, t) for t in ends] or ["no episode ended"]
    print(path)
    print(f"{args.steps} env steps in {time.perf_counter() - started:.1f} s: " + ", ".join(outcomes))


def _describe(results: StepResult, t: int) -> str:
    for name in ("success", "failure", "unstable", "truncated"):
        if results.__getattribute__(name)[t]:
            return f"{name} at step {t + 1}"
    raise AssertionError("a done step has one of the outcome flags")
