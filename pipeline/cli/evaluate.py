"""`kforge evaluate POLICY [--on SETS] [--episodes K] [--greedy]`: success rates of a trained BC policy beside the
no-op and random policies (and the experts' recorded success) on the dataset's, unseen and hand-designed levels."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path

from kforge.pipeline.cli import add_common_options, fail

DEFAULT_SETS = "train,unseen,hand"
REPORT_FILE = "evaluation.json"
"""Default report file, in the policy's run directory."""


def main(argv: Sequence[str] | None = None, prog: str | None = None) -> None:
    """Evaluate a BC policy (a `kforge bc train` run directory) on the dataset's training levels (first episodes from
    each level's start and from stored mid-trajectory states), on unseen levels of the dataset's split, and on
    Kinetix's hand-designed levels of its size, beside the no-op and uniform random policies; prints a table and
    writes the JSON report."""
    args, sets = _parse_args(argv, prog)
    from kforge.pipeline.learning import run_config_file

    try:
        run_config_file(args.policy)
    except FileNotFoundError as error:
        raise fail(error) from None
    result = _evaluate(args, sets)

    from kforge.pipeline.learning import report_table

    out = Path(args.out) if args.out else Path(args.policy) / REPORT_FILE
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1))
    print(json.dumps(result, indent=1) if args.json else f"{report_table(result)}\nreport: {out}")


UNSEEN_LEVELS = 512
"""Unseen levels played by default: the learning layer's `UNSEEN_LEVELS`, named here so that parsing imports nothing
heavy (tests/pipeline/test_cli_fast.py checks that they agree)."""


def _parse_args(argv: Sequence[str] | None, prog: str | None) -> tuple[argparse.Namespace, tuple[str, ...]]:
    """(the arguments, the level sets to play), checked."""
    parser = argparse.ArgumentParser(prog=prog, description=main.__doc__)
    parser.add_argument("policy", help="a BC run directory (kforge bc train's output_dir)")
    parser.add_argument(
        "--on",
        default=DEFAULT_SETS,
        help=f"comma-separated level sets among train, validation, unseen, hand (default {DEFAULT_SETS})",
    )
    parser.add_argument("--episodes", type=int, default=16, help="episodes per start state (default 16)")
    parser.add_argument("--greedy", action="store_true", help="act with the most probable choice per action slot")
    parser.add_argument(
        "--unseen-levels", type=int, default=UNSEEN_LEVELS, help=f"unseen levels to play (default {UNSEEN_LEVELS})"
    )
    parser.add_argument("--max-levels", type=int, help="play at most this many levels of each set")
    parser.add_argument("--step", type=int, help="the checkpoint to evaluate (default the latest)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the episodes and of the stored starts drawn")
    parser.add_argument("--out", help=f"JSON report file (default POLICY/{REPORT_FILE})")
    parser.add_argument("--json", action="store_true", help="print the report as JSON instead of the table")
    args = add_common_options(parser).parse_args(argv)
    sets = tuple(name.strip() for name in args.on.split(",") if name.strip())
    for name, value in (("--episodes", args.episodes), ("--unseen-levels", args.unseen_levels)):
        if value < 1:
            parser.error(f"{name} must be >= 1, got {value}")
    if args.max_levels is not None and args.max_levels < 1:
        parser.error(f"--max-levels must be >= 1, got {args.max_levels}")

    from kforge.pipeline.learning import LEVEL_SETS

    unknown = [name for name in sets if name not in LEVEL_SETS]
    if unknown or not sets:
        parser.error(
            f"--on: unknown level set {unknown[0] if unknown else args.on!r}; choose among {', '.join(LEVEL_SETS)}"
        )
    return args, sets


def _evaluate(args: argparse.Namespace, sets: tuple[str, ...]) -> dict:
    """The evaluation report of the policy's checkpoint on `sets`, progress on stderr."""
    from kforge.engine import use_deterministic_ops
    from kforge.pipeline.learning import Episodes, evaluate_policy, load_policy
    from kforge.pipeline.storage import DatasetError

    use_deterministic_ops()  # before the first computation: repeatable on GPUs too

    try:
        policy = load_policy(args.policy, args.step)
        return evaluate_policy(
            policy,
            sets,
            episodes=Episodes(count=args.episodes, seed=args.seed, greedy=args.greedy),
            unseen_levels=args.unseen_levels,
            max_levels=args.max_levels,
            report=lambda line: print(line, file=sys.stderr),
        )
    except (DatasetError, FileNotFoundError, ValueError) as error:
        if args.debug:
            raise
        raise fail(error) from error
