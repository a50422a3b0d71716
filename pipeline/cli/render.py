"""`kforge render LEVEL`: play a level file (or a bundled level) with a simple policy and write the episode as a
GIF; the arguments are checked before JAX is imported."""

from __future__ import annotations

import argparse
import time
from collections.abc import Sequence
from pathlib import Path

from kforge.pipeline.cli import PHYSICS_SCHEME_NAMES, PLAY_PHYSICS_SCHEME, POLICY_NAMES, add_common_options

DEFAULT_OUT_DIR = Path("outputs")
"""Folder of the GIF unless --out names one: outputs/<level name>.gif."""

OUTCOMES = ("success", "failure", "unstable", "truncated")
"""Step-result flags that end an episode, in the order an ended episode is described by."""


def _parser(prog: str | None) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=prog, description=main.__doc__)
    parser.add_argument(
        "level", type=Path, help="Kinetix level JSON file (sizes s, m or l) or bundled name (s/h0_weak_thrust)"
    )
    parser.add_argument("--policy", choices=POLICY_NAMES, default=POLICY_NAMES[0])
    parser.add_argument("--steps", type=int, default=256, help="env steps to play (default 256, one episode)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the random policy")
    parser.add_argument("--out", type=Path, help="GIF path (default outputs/<level name>.gif)")
    parser.add_argument(
        "--physics",
        choices=PHYSICS_SCHEME_NAMES,
        default=PLAY_PHYSICS_SCHEME,
        help=f"physics scheme, as a job's env.physics (default {PLAY_PHYSICS_SCHEME}: Kinetix's play)",
    )
    return add_common_options(parser)


def main(argv: Sequence[str] | None = None, prog: str | None = None) -> None:
    """Play LEVEL (a Kinetix level JSON file) and write a GIF of it; prints the path and how episodes ended."""
    parser = _parser(prog)
    args = parser.parse_args(argv)
    if args.steps < 1:
        parser.error("--steps must be at least 1")

    import jax
    import numpy as np

    from kforge.engine import physics_scheme
    from kforge.env import Policy, load_level, record_episode, under_scheme, write_state_gif

    loaded = load_level(args.level)
    params, static = under_scheme(physics_scheme(args.physics), loaded.params, loaded.static)
    out = args.out or DEFAULT_OUT_DIR / f"{args.level.stem}.gif"
    started = time.perf_counter()
    states, results = record_episode(
        loaded.level, params, static, Policy(args.policy), jax.random.key(args.seed), args.steps
    )
    path = write_state_gif(jax.device_get(states), static, out)
    results = jax.device_get(results)
    ends = np.flatnonzero(results.done)
    outcomes = [next(f"{name} at step {t + 1}" for name in OUTCOMES if getattr(results, name)[t]) for t in ends]
    print(path)
    print(
        f"{args.steps} env steps in {time.perf_counter() - started:.1f} s: "
        + (", ".join(outcomes) or "no episode ended")
    )
