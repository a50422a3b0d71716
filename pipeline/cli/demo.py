"""`kforge demo`: simulate a small engine scene (a motorised vehicle with a thruster and a stacked box, a ball) and
write it as a GIF; the arguments are checked before JAX is imported."""

from __future__ import annotations

import argparse
from collections.abc import Sequence

from kforge.pipeline.cli import add_common_options

DEFAULT_OUT = "outputs/engine_demo.gif"
DEFAULT_STEPS = 240  # 4 s at the default dt of 1/60 s
DEMO_RENDER_EVERY = 2
"""The demo renders every this many steps (`engine.demo.RENDER_EVERY`), so it needs at least this many."""


def main(argv: Sequence[str] | None = None, prog: str | None = None) -> None:
    """Simulate the demo scene and write the GIF; prints its path and a summary of the run."""
    parser = add_common_options(argparse.ArgumentParser(prog=prog, description=main.__doc__))
    parser.add_argument("--out", default=DEFAULT_OUT, help=f"GIF path (default {DEFAULT_OUT})")
    parser.add_argument("--steps", type=int, default=DEFAULT_STEPS, help=f"physics steps (default {DEFAULT_STEPS})")
    args = parser.parse_args(argv)
    if args.steps < DEMO_RENDER_EVERY:
        parser.error(f"--steps must be at least {DEMO_RENDER_EVERY}")

    from kforge.engine import write_demo

    path, summary = write_demo(args.out, args.steps)
    print(path)
    print(summary)
