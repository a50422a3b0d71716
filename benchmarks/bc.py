"""Proof of use: behaviour cloning on a split 1M/s dataset, with more and more training levels, evaluated on the
training levels, on unseen levels of the split and on the hand-designed s levels, beside the no-op and random policies.

    python -m benchmarks.bc --dataset outputs/1M-s-local --train-levels 16 32 64 --steps 1000
    python -m benchmarks.bc --generate 64 --train-levels 16 64   # first makes the dataset (kforge run 1M/s)

Each training-level count trains the same model for the same number of gradient steps on the dataset's first N
kept levels (by level id; 10 % of them held out for validation), then plays every level set with the trained policy
and the baselines on the same episode keys. Reports, per count: success rates (BC, no-op, random, and the experts'
recorded success on the training levels), validation accuracy, and the share of step time spent waiting for the
loader. Goals (issue "Learning from the data"): BC beats random on unseen levels; unseen success rises with the
number of training levels; training-level success approaches the experts'; loader wait <= 5 % of step time.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from benchmarks.machine import describe_machine
from kforge.pipeline.learning import evaluate_policy, load_bc_config, load_policy, train_bc

LOADER_WAIT_TARGET = 0.05
"""Target share of BC step time spent waiting for the loader."""


def generate(num_levels: int, output_dir: Path, workers: int) -> None:
    """Make (or resume) split 1M/s at the release budget on its first `num_levels` levels."""
    command = [
        sys.executable,
        "-m",
        "pipeline",
        "run",
        "1M/s",
        "--scale",
        "local",
        f"output_dir={output_dir}",
        f"split.num_levels={num_levels}",
        f"ray.num_workers={workers}",
        "work.levels_per_batch=16",
        "--no-progress",
    ]
    subprocess.run(command, check=True)


def run_count(args, count: int) -> dict:
    """Train on the dataset's first `count` kept levels and evaluate; the row of the report."""
    run_dir = Path(args.work_dir) / f"bc-{count}-levels"
    overrides = [
        f"output_dir={run_dir}",
        f"train.levels={count}",
        f"train.num_steps={args.steps}",
        f"train.batch_size={args.batch_size}",
        f"model.architecture={args.architecture}",
        f"validation.every_steps={max(1, args.steps // 4)}",
        f"checkpoint.every_steps={args.steps}",
        "tracking.wandb=disabled",
    ]
    config = load_bc_config(args.dataset, overrides)
    started = time.perf_counter()
    summary = train_bc(config, show_progress=not args.no_progress, report=lambda line: print(line, file=sys.stderr))
    trained = time.perf_counter() - started
    started = time.perf_counter()
    result = evaluate_policy(
        load_policy(run_dir),
        ("train", "unseen", "hand"),
        episodes=args.episodes,
        unseen_levels=args.unseen_levels,
        seed=0,
        report=lambda line: print(line, file=sys.stderr),
    )
    return {
        "training_levels": summary.train_levels,
        "validation_levels": summary.validation_levels,
        "steps": summary.steps,
        "train_loss": summary.train_loss,
        "validation_loss": summary.validation_loss,
        "validation_accuracy": summary.validation_accuracy,
        "loader_wait_share": summary.loader_wait_share,
        "transitions_per_s": summary.transitions_per_s,
        "train_seconds": trained,
        "evaluation_seconds": time.perf_counter() - started,
        "evaluation": result,
    }


def _rate(row: dict, level_set: str, policy: str) -> float:
    return row["evaluation"]["sets"][level_set]["from_start"][policy]["success"]


def print_table(rows: list[dict]) -> None:
    print(
        f"{'levels':>6} | {'train: BC':>9} {'expert':>6} {'random':>6} {'noop':>5} | {'unseen: BC':>10} {'random':>6} "
        f"{'noop':>5} | {'hand: BC':>8} {'random':>6} {'noop':>5} | {'val acc':>7} {'wait':>6}"
    )
    for row in rows:
        cells = [
            f"{_rate(row, 'train', 'bc'):>9.3f}",
            f"{row['evaluation']['sets']['train']['from_start']['expert_recorded']['success']:>6.3f}",
            f"{_rate(row, 'train', 'random'):>6.3f}",
            f"{_rate(row, 'train', 'noop'):>5.3f} |",
            f"{_rate(row, 'unseen', 'bc'):>10.3f}",
            f"{_rate(row, 'unseen', 'random'):>6.3f}",
            f"{_rate(row, 'unseen', 'noop'):>5.3f} |",
            f"{_rate(row, 'hand', 'bc'):>8.3f}",
            f"{_rate(row, 'hand', 'random'):>6.3f}",
            f"{_rate(row, 'hand', 'noop'):>5.3f} |",
            f"{row['validation_accuracy'] or float('nan'):>7.3f}",
            f"{100 * row['loader_wait_share']:>5.1f}%",
        ]
        print(f"{row['training_levels']:>6} | " + " ".join(cells))


def goals(rows: list[dict]) -> dict:
    """Which of the issue's goals the rows meet."""
    unseen = [_rate(row, "unseen", "bc") for row in rows]
    return {
        "bc_beats_random_on_unseen": all(_rate(row, "unseen", "bc") > _rate(row, "unseen", "random") for row in rows),
        "unseen_success_rises_with_levels": all(b >= a for a, b in zip(unseen, unseen[1:], strict=False)),
        "train_success_over_expert": [
            _rate(row, "train", "bc")
            / max(row["evaluation"]["sets"]["train"]["from_start"]["expert_recorded"]["success"], 1e-9)
            for row in rows
        ],
        "loader_wait_within_target": all(row["loader_wait_share"] <= LOADER_WAIT_TARGET for row in rows),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", help="a split 1M/s dataset (default: the one --generate makes)")
    parser.add_argument("--generate", type=int, help="first make split 1M/s on this many levels (resumes)")
    parser.add_argument("--workers", type=int, default=2, help="Ray workers of --generate")
    parser.add_argument("--train-levels", type=int, nargs="+", default=[16, 64, 256])
    parser.add_argument("--steps", type=int, default=1000, help="gradient steps of every run")
    parser.add_argument("--batch-size", type=int, default=16)
    parser.add_argument("--architecture", default="transformer", choices=["mlp", "transformer"])
    parser.add_argument("--episodes", type=int, default=8, help="episodes per start state in evaluation")
    parser.add_argument("--unseen-levels", type=int, default=256)
    parser.add_argument("--work-dir", default="outputs/benchmarks/bc", help="folder of the BC runs")
    parser.add_argument("--no-progress", action="store_true")
    parser.add_argument("--json", help="write the report here")
    args = parser.parse_args()
    if args.dataset is None:
        if args.generate is None:
            parser.error("give --dataset, or --generate N to make one")
        args.dataset = str(Path(args.work_dir) / "dataset-1M-s")
    if args.generate is not None:
        generate(args.generate, Path(args.dataset), args.workers)
    rows = [run_count(args, count) for count in args.train_levels]
    print_table(rows)
    report = {
        "machine": describe_machine(),
        "dataset": os.fspath(args.dataset),
        "settings": {key: value for key, value in vars(args).items() if key not in ("json", "no_progress")},
        "rows": rows,
        "goals": goals(rows),
    }
    print(json.dumps(report["goals"], indent=1))
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
