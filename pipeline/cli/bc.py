"""`kforge bc train DATASET [key=value ...]`: behaviour cloning on a dataset; re-running on the same run directory
resumes from its latest checkpoint."""

from __future__ import annotations

import argparse
import dataclasses
import json
import shlex
import signal
import sys
from collections.abc import Sequence

from kforge.pipeline.cli import EXIT_INTERRUPTED, add_common_options, fail, load_config_or_exit, require_dataset


def _terminate_as_interrupt(signum, frame):
    raise KeyboardInterrupt


def main(argv: Sequence[str] | None = None, prog: str | None = None) -> None:
    """Behaviour cloning on a kforge dataset (`train`): a policy trained on the stored expert actions, validated
    on held-out levels, checkpointed; Ctrl-C or SIGTERM checkpoints and stops, re-running resumes."""
    args = _parse_train_args(argv, prog)
    require_dataset(args.dataset)

    from kforge.pipeline.generation import to_yaml
    from kforge.pipeline.learning import load_bc_config

    config = load_config_or_exit(lambda: load_bc_config(args.dataset, args.overrides, args.config), args.debug)
    if args.print_config:
        print(to_yaml(config), end="")
        return
    summary = _train(config, args, argv)
    if args.json:
        print(json.dumps(dataclasses.asdict(summary), indent=1))
        return
    print(_closing_lines(summary))


def _parse_train_args(argv: Sequence[str] | None, prog: str | None) -> argparse.Namespace:
    """The `train` action's arguments (the common options may come before the action or after it)."""
    parser = argparse.ArgumentParser(prog=prog, description=main.__doc__)
    parser.add_argument("action", choices=["train"], help="train: train (or resume) a BC policy on a dataset")
    parser.add_argument("arguments", nargs=argparse.REMAINDER, help="the action's arguments (ACTION --help)")
    add_common_options(parser)
    top = parser.parse_args(argv)
    train = argparse.ArgumentParser(prog=f"{prog} train", description=main.__doc__)
    train.add_argument("dataset", help="the dataset: a local path, s3://... or gs://...")
    train.add_argument(
        "overrides",
        nargs="*",
        help="dotlist overrides of configs/bc.yaml, e.g. train.num_steps=500 model.architecture=mlp",
    )
    train.add_argument("--config", help="a BC config YAML used instead of configs/bc.yaml")
    train.add_argument(
        "--print-config", action="store_true", help="print the resolved config (each key's type and meaning) and exit"
    )
    train.add_argument("--no-progress", action="store_true", help="no progress bar")
    train.add_argument("--json", action="store_true", help="end with the summary as JSON (for scripts)")
    train.add_argument("--stop-after", type=int, help="stop (checkpointed) after this many steps of this invocation")
    add_common_options(train)
    args = train.parse_intermixed_args(
        top.arguments + [option for option in ("--debug", "--verbose") if getattr(top, option[2:])]
    )
    if args.stop_after is not None and args.stop_after < 1:
        train.error(f"--stop-after must be >= 1, got {args.stop_after}")
    return args


def _train(config, args: argparse.Namespace, argv: Sequence[str] | None):
    """Train (or resume) the run, SIGTERM taken as Ctrl-C; its summary. An interruption exits saying how to resume."""
    from kforge.engine import use_deterministic_ops
    from kforge.pipeline.generation import ConfigError
    from kforge.pipeline.learning import TrainingInterrupted, train_bc
    from kforge.pipeline.storage import DatasetError

    use_deterministic_ops()  # before the first computation: repeatable on GPUs too

    previous = signal.signal(signal.SIGTERM, _terminate_as_interrupt)
    try:
        return train_bc(
            config,
            show_progress=not args.no_progress,
            report=lambda line: print(line, file=sys.stderr),
            stop_after_steps=args.stop_after,
            verbose=args.verbose,
        )
    except TrainingInterrupted as interrupted:
        resume = shlex.join(["kforge", "bc", *(argv if argv is not None else sys.argv[2:])])
        print(f"{interrupted}; resume with: {resume}", file=sys.stderr)
        raise SystemExit(EXIT_INTERRUPTED) from None
    except (ConfigError, DatasetError, FileNotFoundError, ValueError) as error:
        if args.debug:
            raise
        raise fail(error) from error
    finally:
        signal.signal(signal.SIGTERM, previous)


def _closing_lines(summary) -> str:
    """The run's closing figures and the command that evaluates it."""
    validation = (
        "no validation levels"
        if summary.validation_loss is None
        else f"validation loss {summary.validation_loss:.3f}, accuracy {summary.validation_accuracy:.3f}"
    )
    return (
        f"{summary.run_dir}: step {summary.steps}, {summary.train_levels} training and {summary.validation_levels} "
        f"validation levels; training loss {summary.train_loss:.3f}, accuracy {summary.train_accuracy:.3f}; "
        f"{validation}; {summary.transitions_per_s:,.0f} transitions/s, waiting for data "
        f"{100 * summary.loader_wait_share:.1f} % of the time\n"
        f"  kforge evaluate {summary.run_dir}    # success rates beside the no-op and random policies"
    )
