"""Proof of use: behaviour cloning on a split's dataset with more and more training levels, each policy evaluated on
its training levels, on unseen levels of the split and on Kinetix's hand-designed levels beside the no-op and random
policies, the best one played inside kinetix-env too, with Kinetix's published general agent as an anchor.

    python -m benchmarks.bc --dataset DATASET --train-levels 16 64 256 512 \\
        --json benchmarks/results/bc_scaling.json --plot docs/bc_scaling.png

Stages, each kept in `--work-dir/stages/<stage>.json` once done, so an interrupted report resumes at the stage it
stopped in (and BC training itself resumes from its checkpoints):
- `train-N` for each N of `--train-levels` the dataset holds: `kforge bc train` on the dataset's first N kept levels
  (by id; `validation.fraction` of them held out), under one budget rule for every N: `--epochs` passes over the
  training trajectories in batches of `min(--batch-size, training trajectories)` (the entity transformer, AdamW,
  gradient clipping: configs/bc.yaml);
- `evaluate-N`: `pipeline.learning.evaluate_policy` on the train, unseen (`--unseen-levels` filter-kept levels from
  the fixed split index 2^31) and hand (all 74) sets, `--episodes` first episodes per start, the no-op and random
  policies on the same starts with the same keys;
- `train-mlp-N` and `warm-start-*` (`--warm-start-levels`, 0 leaves them out): benchmarks/warm_start.py, PPO
  fine-tuned from an MLP BC policy of the largest N against PPO from scratch on unseen levels, paired by level;
- `transfer`: benchmarks/kinetix_transfer.py with the policy of the largest N: the hand-designed levels and
  `--kinetix-levels` levels of Kinetix's own sampler played in kinetix-env 3.0.2 and in kforge (`--skip-transfer`
  leaves it out).
The stored report holds every stage that is done; counts the dataset does not hold yet are listed as missing.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from pathlib import Path

from benchmarks.kinetix_transfer import SAMPLED_LEVELS, transfer
from benchmarks.kinetix_venv import DEFAULT_KINETIX_VENV, REPOSITORY
from benchmarks.machine import describe_machine, provenance
from benchmarks.stages import stage
from benchmarks.warm_start import warm_start
from kforge.pipeline.learning import (
    UNSEEN_FIRST_LEVEL,
    Episodes,
    evaluate_policy,
    kept_levels,
    load_bc_config,
    load_policy,
    train_bc,
)

SFL_ANCHORS = {
    "source": (
        "Kinetix (Matthews et al., 2025), its general SFL agent's success rates as published with its checkpoints "
        "(Kinetix-Checkpoints); not run here"
    ),
    "hand": {"s": 0.42, "m": 0.32, "l": 0.11},
    "random": {"s": 0.33, "m": 0.24, "l": 0.16},
}
"""Kinetix's general agent (trained on millions of sampled levels by SFL) on its hand-designed and on randomly
sampled levels, by size."""

EPOCHS_PER_VALIDATION = 5
"""Passes over the training trajectories between two validations: the plateau rule (configs/bc.yaml's patience) then
stops a run after `patience * EPOCHS_PER_VALIDATION` epochs without a better validation loss, whatever the count."""

TRAJECTORIES_PER_BATCH = 32
"""Trajectories per BC batch (Kinetix's offline BC), or all training trajectories when fewer."""

VALIDATION_FRACTION = 0.1
"""Share of each count's levels held out for validation (configs/bc.yaml's default)."""


def budget(levels: int, epochs: int, batch_size: int) -> dict:
    """The budget rule: at most `epochs` passes over the training trajectories (one per level) in batches of at most
    `batch_size`, validated every `EPOCHS_PER_VALIDATION` passes (so the plateau rule stops every count alike)."""
    validation = min(levels - 1, max(1, math.ceil(VALIDATION_FRACTION * levels))) if levels > 1 else 0
    trajectories = levels - validation
    batch = min(batch_size, trajectories)
    steps_per_epoch = trajectories / batch
    return {
        "batch_size": batch,
        "num_steps": max(1, math.ceil(epochs * steps_per_epoch)),
        "validate_every_steps": max(1, math.ceil(EPOCHS_PER_VALIDATION * steps_per_epoch)),
    }


def train_stage(args, count: int, log, architecture: str | None = None) -> dict:
    """BC on the dataset's first `count` kept levels under the budget rule: configs/bc.yaml's network, or another
    `architecture` (the run directory then names it)."""
    run_dir = Path(args.work_dir) / (f"bc-{architecture}-{count}-levels" if architecture else f"bc-{count}-levels")
    rule = budget(count, args.epochs, args.batch_size)
    overrides = [
        *([f"model.architecture={architecture}"] if architecture else []),
        f"output_dir={run_dir}",
        f"train.levels={count}",
        f"train.num_steps={rule['num_steps']}",
        f"train.batch_size={rule['batch_size']}",
        f"validation.every_steps={rule['validate_every_steps']}",
        f"checkpoint.every_steps={rule['validate_every_steps']}",
        "tracking.wandb=disabled",
    ]
    summary = train_bc(load_bc_config(args.dataset, overrides), show_progress=False, report=log)
    curve = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines() if line]
    return {
        "run_dir": str(run_dir),
        "overrides": overrides,
        "training_levels": summary.train_levels,
        "validation_levels": summary.validation_levels,
        "steps": summary.steps,
        "train_loss": summary.train_loss,
        "validation_loss": summary.validation_loss,
        "validation_accuracy": summary.validation_accuracy,
        "transitions_per_s": summary.transitions_per_s,
        "curve": curve,
    }


def evaluate_stage(args, run_dir: str, log) -> dict:
    return evaluate_policy(
        load_policy(run_dir),
        ("train", "unseen", "hand"),
        episodes=Episodes(count=args.episodes, seed=0),
        unseen_levels=args.unseen_levels,
        report=log,
    )


def _success(entry: dict, player: str) -> str:
    rates = entry["from_start"][player]
    return f"{rates['success']:.3f}±{rates['success_se']:.3f}"


def table(rows: list[dict]) -> str:
    """The scaling table: per count, BC's success on each set beside the baselines (and the experts' on train)."""
    lines = [
        f"{'levels':>6} {'steps':>6} | {'train BC':>12} {'expert':>6} {'random':>6} | {'unseen BC':>12} "
        f"{'random':>12} {'noop':>5} {'BC-random':>13} | {'hand BC':>12} {'random':>12} {'BC-random':>13}"
    ]
    for row in rows:
        sets = row["evaluation"]["sets"]
        train, unseen, hand = sets["train"], sets["unseen"], sets["hand"]
        expert, train_random = (
            train["from_start"]["expert_recorded"]["success"],
            train["from_start"]["random"]["success"],
        )
        gains = [s["from_start"]["bc_minus_random"] for s in (unseen, hand)]
        gain = [f"{g['difference']:+.3f}±{g['se']:.3f}" for g in gains]
        lines.append(
            f"{row['training']['training_levels']:>6} {row['training']['steps']:>6} | {_success(train, 'bc'):>12} "
            f"{expert:>6.3f} {train_random:>6.3f} | {_success(unseen, 'bc'):>12} {_success(unseen, 'random'):>12} "
            f"{unseen['from_start']['noop']['success']:>5.3f} {gain[0]:>13} | {_success(hand, 'bc'):>12} "
            f"{_success(hand, 'random'):>12} {gain[1]:>13}"
        )
    return "\n".join(lines)


def plot(rows: list[dict], path: Path) -> None:
    """Success against training levels on each set (BC, random, no-op; the experts' on train), the SFL anchors as
    dashed lines on hand and unseen (its random-level figure of the same size)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    counts = [row["training"]["training_levels"] for row in rows]
    figure, axes = plt.subplots(1, 3, figsize=(12, 3.6), sharey=True)
    for axis, name in zip(axes, ("train", "unseen", "hand"), strict=True):
        entries = [row["evaluation"]["sets"][name]["from_start"] for row in rows]
        for player, style in (("bc", "o-"), ("random", "s--"), ("noop", "x:")):
            axis.errorbar(
                counts,
                [e[player]["success"] for e in entries],
                yerr=[e[player]["success_se"] for e in entries],
                fmt=style,
                capsize=3,
                label={"bc": "BC", "random": "random", "noop": "no-op"}[player],
            )
        if name == "train":
            axis.plot(counts, [e["expert_recorded"]["success"] for e in entries], "d-", label="experts (recorded)")
        anchor = {"hand": SFL_ANCHORS["hand"]["s"], "unseen": SFL_ANCHORS["random"]["s"]}.get(name)
        if anchor is not None:
            axis.axhline(anchor, color="grey", linestyle="--", linewidth=1, label="SFL (published, s)")
        axis.set_xscale("log", base=2)
        axis.set_xticks(counts, [str(c) for c in counts])
        axis.set_title({"train": "training levels", "unseen": "unseen levels (s)", "hand": "hand-designed (74)"}[name])
        axis.set_xlabel("training levels")
        axis.set_ylim(0, 1)
        axis.legend(fontsize=7)
    axes[0].set_ylabel("success (first episode)")
    figure.tight_layout()
    figure.savefig(path, dpi=110)


def without_machine_paths(text: str, args) -> str:
    """`text` with the dataset's and the work directory's paths on this machine named DATASET and WORK_DIR, and the
    checkout's files (the bundled levels) by their paths in the repository."""
    for path, name in ((args.work_dir, "WORK_DIR"), (Path(args.dataset), "DATASET")):
        for spelling in sorted({str(path.absolute()), str(path)}, key=len, reverse=True):
            text = text.replace(json.dumps(spelling)[1:-1], name)
    return text.replace(json.dumps(f"{REPOSITORY}{os.sep}")[1:-1], "")


def warm_start_stage(args, count: int, log) -> dict:
    """`train-mlp-N`: BC with an MLP over flat observations on the largest count under the same budget rule (PPO's
    actor reads flat observations); then benchmarks/warm_start.py from it, its programs kept as stages."""
    rule = budget(count, args.epochs, args.batch_size)
    settings = {"dataset": Path(args.dataset).name, "levels": count, "epochs": args.epochs, "architecture": "mlp"}
    training = stage(
        args.work_dir, f"train-mlp-{count}", settings | rule, lambda: train_stage(args, count, log, "mlp"), log
    )
    result = warm_start(
        args.dataset, training["run_dir"], args.warm_start_levels, args.warm_start_steps, args.work_dir, log
    )
    return {"bc_training": training} | result


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", required=True, help="a dataset made by kforge run")
    parser.add_argument("--train-levels", type=int, nargs="+", default=[16, 64, 256, 512])
    parser.add_argument("--epochs", type=int, default=200, help="passes over the training trajectories, every count")
    parser.add_argument("--batch-size", type=int, default=TRAJECTORIES_PER_BATCH)
    parser.add_argument("--episodes", type=int, default=8, help="first episodes per start state in evaluation")
    parser.add_argument("--unseen-levels", type=int, default=512)
    parser.add_argument("--kinetix-levels", type=int, default=SAMPLED_LEVELS, help="levels of Kinetix's sampler")
    parser.add_argument("--skip-transfer", action="store_true", help="leave out the kinetix-env stage")
    parser.add_argument("--kinetix-venv", type=Path, default=DEFAULT_KINETIX_VENV)
    parser.add_argument("--warm-start-levels", type=int, default=32, help="unseen levels of the warm start; 0: none")
    parser.add_argument("--warm-start-steps", type=int, default=1_000_000, help="PPO env steps per level and arm")
    parser.add_argument("--work-dir", type=Path, default=Path("outputs/benchmarks/bc"), help="runs and stage results")
    parser.add_argument("--json", type=Path, help="write the report here")
    parser.add_argument("--plot", type=Path, help="write the scaling plot here (PNG)")
    args = parser.parse_args(argv)

    def log(line: str) -> None:
        print(line, file=sys.stderr, flush=True)

    held = len(kept_levels(args.dataset))
    counts = sorted({count for count in args.train_levels if count <= held})
    missing = sorted(set(args.train_levels) - set(counts))
    if missing:
        log(f"{args.dataset} holds {held} kept levels: no run for {missing}")
    rows = []
    for count in counts:
        rule = budget(count, args.epochs, args.batch_size)
        settings = {"dataset": Path(args.dataset).name, "levels": count, "epochs": args.epochs} | rule
        training = stage(args.work_dir, f"train-{count}", settings, lambda c=count: train_stage(args, c, log), log)
        evaluation_settings = settings | {"episodes": args.episodes, "unseen_levels": args.unseen_levels}
        evaluation = stage(
            args.work_dir,
            f"evaluate-{count}",
            evaluation_settings,
            lambda run=training["run_dir"]: evaluate_stage(args, run, log),
            log,
        )
        rows.append({"levels": count, "budget": rule, "training": training, "evaluation": evaluation})
        log(table(rows))
    command = [{str(args.dataset): "DATASET", str(args.work_dir): "WORK_DIR"}.get(a, a) for a in sys.argv]
    report = provenance(command) | {  # the dataset named by its folder: no machine path in the report
        "machine": describe_machine(),
        "dataset": {"path": Path(args.dataset).name, "kept_levels": held},
        "budget_rule": {
            "epochs": args.epochs,
            "batch_size": args.batch_size,
            "validation_fraction": VALIDATION_FRACTION,
        },
        "unseen_first_level": UNSEEN_FIRST_LEVEL,
        "missing_counts": missing,
        "rows": rows,
        "anchors": SFL_ANCHORS,
    }
    if rows and not args.skip_transfer:
        run_dir = Path(rows[-1]["training"]["run_dir"])
        settings = {"run": str(run_dir), "kinetix_levels": args.kinetix_levels, "episodes": args.episodes}
        report["transfer"] = stage(
            args.work_dir,
            "transfer",
            settings,
            lambda: transfer(
                run_dir, args.kinetix_levels, args.episodes, 0, 0, args.work_dir / "transfer", args.kinetix_venv, log
            ),
            log,
        )
    if rows and args.warm_start_levels:
        report["warm_start"] = warm_start_stage(args, rows[-1]["levels"], log)
    print(table(rows))
    if args.json:
        args.json.write_text(without_machine_paths(json.dumps(report, indent=1), args) + "\n")
    if args.plot and rows:
        plot(rows, args.plot)


if __name__ == "__main__":
    main()
