"""End-to-end generation throughput, time outside expert training and rollout, and bytes on disk per transition.

For each size it runs the same small job (embedded local Ray, a fresh output directory) once per worker count and
prints: stored transitions per second, expert env steps per second, the share of worker time spent outside
training and rollout (sampling, filtering, writing, coordination, start-up), overall and after each worker's first
level batch (which compiles every program), bytes of shard files per stored transition next to Kinetix-Offline's
(release figures, docs/kinetix.md) and by field group, the trajectories per second the loader reads back, and whether
every worker count wrote the same data.
`--json` prints one JSON document instead. `--storage s3` measures the storage layer instead, against an S3 API
server (moto) on 127.0.0.1: transitions written per second and the loader's read rate from S3 against a local
folder, with and without prefetch (benchmarks/object_storage.py). `--cost` measures what a dataset costs instead:
kept levels and transitions per machine-hour of split 1M/s at its release budget, fixed and adaptive expert budgets
side by side, against Kinetix's PPO measured in the same run (benchmarks/pipeline_cost.py).

    python -m benchmarks.pipeline_speed
    python -m benchmarks.pipeline_speed --sizes s --levels 32 --workers 1 2 --json
    python -m benchmarks.pipeline_speed --storage s3 --sizes s --levels-per-batch 8 --batches-per-shard 4
    python -m benchmarks.pipeline_speed --cost --levels 16 --levels-per-batch 4 --json
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import json
import sys
import tempfile
import time
from pathlib import Path

import jax

from benchmarks import pipeline_cost
from benchmarks.machine import describe_machine, provenance
from kforge.pipeline.generation import load_config, run_job
from kforge.pipeline.reading import TrajectoryDatasetManager
from kforge.pipeline.storage import DATA_DIR, STATE_PREFIX, iter_records, open_dataset

KINETIX_OFFLINE_BYTES_PER_TRANSITION = {"s": 80.4, "m": 110.9, "l": 306.0}
"""Kinetix-Offline 1M splits: bytes on disk per transition (GB = 1e9), docs/kinetix.md, released splits."""

TARGET_SHARE_OF_KINETIX_BYTES = 0.5
TARGET_OUTSIDE_SHARE = 0.05
TRAINING_PHASES = ("train", "collect")
"""Provenance phases that are expert training and rollout; every other second of a worker counts as outside."""


def bytes_on_disk(root: Path) -> tuple[int, int]:
    """(bytes of the arrays' shard files, bytes of their zarr.json metadata: fixed per dataset, not per transition)."""
    files = [path for path in (root / DATA_DIR).rglob("*") if path.is_file()]
    metadata = sum(path.stat().st_size for path in files if path.name == "zarr.json")
    return sum(path.stat().st_size for path in files) - metadata, metadata


def bytes_by_group(root: Path) -> dict[str, int]:
    """Shard-file bytes of the dataset's arrays in five groups: per-step state (bodies, counters), the per-step
    solver warm-start caches, per-level state, per-step actions and flags, per-level metadata (`meta/*`,
    `action_mask`)."""
    layout = open_dataset(root).layout
    groups: dict[str, int] = {}
    for spec in layout.fields:
        state = spec.name.startswith(STATE_PREFIX + "/")
        group = {
            (True, True): "per-step state",
            (True, False): "per-level state",
            (False, True): "actions, done, success",
            (False, False): "metadata",
        }[(state, spec.per_step)]
        if spec.is_solver_cache:
            group = "per-step solver caches"
        folder = root / DATA_DIR / spec.name
        size = sum(path.stat().st_size for path in folder.rglob("*") if path.is_file() and path.name != "zarr.json")
        groups[group] = groups.get(group, 0) + size
    return groups


LOADER_BATCH = 8
"""Trajectories per loader batch when measuring read speed."""

LOADER_TRAJECTORIES = 256
"""Trajectories the loader reads (after one untimed batch) when measuring read speed."""


def loader_rate(root: Path, kept: int) -> float | None:
    """Trajectories per second that `TrajectoryDatasetManager` delivers (shuffled, decoded, on the JAX device)."""
    if kept == 0:
        return None
    manager = TrajectoryDatasetManager(root, batch_size=min(LOADER_BATCH, kept), seed=0)
    jax.block_until_ready(manager.load_next_batch().action)
    batches = max(1, LOADER_TRAJECTORIES // manager.batch_size)
    clock = time.perf_counter()
    for _ in range(batches):
        jax.block_until_ready(manager.load_next_batch().action)
    return batches * manager.batch_size / (time.perf_counter() - clock)


def steady_state_outside_share(records: list) -> float | None:
    """Share of worker time outside training and rollout over the level batches after each worker's first one
    (which pays for compiling every program): what long jobs with many batches per worker approach."""
    first: dict[str, tuple[int, int]] = {}
    for record in records:
        worker = (record.provenance or {}).get("worker")
        key = (record.shard, record.batch)
        if worker is not None and (worker not in first or key < first[worker]):
            first[worker] = key
    later = [
        record.provenance["seconds"]
        for record in records
        if (record.provenance or {}).get("worker") is not None
        and (record.shard, record.batch) != first[record.provenance["worker"]]
    ]
    total = sum(seconds["total"] for seconds in later)
    if not total:
        return None
    return 1.0 - sum(seconds[phase] for seconds in later for phase in TRAINING_PHASES) / total


def measure(size: str, workers: int, args, scratch: Path) -> dict:
    output = scratch / f"{size}-{workers}w"
    overrides = [
        f"output_dir={output}",
        f"split.name=bench/{size}",
        f"split.size={size}",
        f"split.num_levels={args.levels}",
        f"split.expert_budget={args.budget}",
        f"work.levels_per_batch={args.levels_per_batch}",
        f"work.levels_per_shard={args.levels_per_batch * args.batches_per_shard}",
        f"ppo.num_envs={args.num_envs}",
        f"ppo.num_steps={args.num_steps}",
        f"ray.num_workers={workers}",
        "tracking.wandb=disabled",
    ]
    job = load_config(None, overrides)
    summary = run_job(job, show_progress=False)
    records = list(iter_records(output))
    phases: dict[str, float] = {}
    for record in records:
        for phase, seconds in (record.provenance or {}).get("seconds", {}).items():
            phases[phase] = phases.get(phase, 0.0) + seconds
    kept = sum(record.num_kept for record in records)
    transitions = kept * job.collect.window_steps
    trained = sum(1 for record in records for level in record.levels if level.outcome.has_window)
    wall = summary["seconds"]
    in_training = sum(phases.get(phase, 0.0) for phase in TRAINING_PHASES)
    disk, metadata = bytes_on_disk(output)
    return {
        "size": size,
        "workers": workers,
        "wall_seconds": wall,
        "levels": summary["levels"],
        "outcomes": summary["outcomes"],
        "kept_trajectories": kept,
        "transitions_per_second": transitions / wall,
        "expert_env_steps_per_second": trained * args.budget / wall,
        "phase_seconds": phases,
        "outside_training_share": 1.0 - in_training / (wall * workers),
        "steady_state_outside_training_share": steady_state_outside_share(records),
        "bytes_on_disk": disk,
        "metadata_bytes": metadata,
        "bytes_per_transition": disk / transitions if transitions else None,
        "loader_trajectories_per_second": loader_rate(output, kept),
        "bytes_per_transition_by_group": {
            group: size / transitions for group, size in bytes_by_group(output).items() if transitions
        },
        "data_digests": sorted(
            (record.global_batch, name, entry.data_sha256)
            for record in records
            for name, entry in record.arrays.items()
        ),
    }


def run(args, log=print) -> dict:
    results = []
    with contextlib.ExitStack() as stack:
        if args.keep is None:
            scratch = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="kforge-bench-")))
        else:
            scratch = args.keep
            taken = [f"{size}-{workers}w" for size in args.sizes for workers in args.workers]
            taken = [name for name in taken if (scratch / name).exists()]
            if taken:
                raise SystemExit(f"--keep {scratch}: {', '.join(taken)} already exist (a rerun would resume them)")
        for size in args.sizes:
            for workers in args.workers:
                result = measure(size, workers, args, scratch)
                results.append(result)
                log(_line(result))
    report = {
        **provenance(),
        "machine": describe_machine(),
        "settings": {k: getattr(args, k) for k in ("levels", "budget", "levels_per_batch", "batches_per_shard")},
        "runs": [{k: v for k, v in result.items() if k != "data_digests"} for result in results],
        "same_data_across_worker_counts": {
            size: len({json.dumps(r["data_digests"]) for r in results if r["size"] == size}) == 1 for size in args.sizes
        },
        "bytes_vs_kinetix_offline": {
            r["size"]: r["bytes_per_transition"] / KINETIX_OFFLINE_BYTES_PER_TRANSITION[r["size"]]
            for r in results
            if r["bytes_per_transition"] is not None
        },
    }
    scaling = {}
    for size in args.sizes:
        by_workers = {r["workers"]: r["transitions_per_second"] for r in results if r["size"] == size}
        if 1 in by_workers and by_workers[1] > 0:
            scaling[size] = {workers: rate / by_workers[1] for workers, rate in by_workers.items()}
    report["throughput_vs_one_worker"] = scaling
    return report


def _line(result: dict) -> str:
    per_transition = result["bytes_per_transition"]
    size = result["size"]
    storage = (
        f"{per_transition:6.1f} B/transition ({per_transition / KINETIX_OFFLINE_BYTES_PER_TRANSITION[size]:.2f}x "
        f"Kinetix-Offline's {KINETIX_OFFLINE_BYTES_PER_TRANSITION[size]}, target <= {TARGET_SHARE_OF_KINETIX_BYTES}x)"
        if per_transition is not None
        else "no kept trajectory"
    )
    if per_transition is not None:
        groups = ", ".join(f"{group} {size:.1f}" for group, size in result["bytes_per_transition_by_group"].items())
        storage += f" [{groups}]"
    share = result["steady_state_outside_training_share"]
    steady = "n/a" if share is None else f"{100 * share:4.1f} %"
    rate = result["loader_trajectories_per_second"]
    if rate is not None:
        storage += f"; the loader reads {rate:,.0f} trajectories/s"
    return (
        f"{size} {result['workers']} worker(s): {result['wall_seconds']:6.1f} s, {result['kept_trajectories']} kept of "
        f"{result['levels']} levels, {result['transitions_per_second']:8.1f} transitions/s, "
        f"{result['expert_env_steps_per_second']:8.0f} expert env steps/s, outside training "
        f"{100 * result['outside_training_share']:4.1f} % of wall x workers, {steady} after each worker's first "
        f"batch (target <= {100 * TARGET_OUTSIDE_SHARE:.0f} %), {storage}"
    )


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", nargs="+", default=["s", "m", "l"], choices=["s", "m", "l"])
    parser.add_argument("--workers", nargs="+", type=int, default=[1, 2], help="worker counts to compare")
    parser.add_argument("--levels", type=int, default=32, help="levels per job")
    parser.add_argument("--budget", type=int, default=131072, help="expert env steps per level")
    parser.add_argument("--levels-per-batch", type=int, default=8)
    parser.add_argument("--batches-per-shard", type=int, default=2)
    parser.add_argument("--num-envs", type=int, default=16)
    parser.add_argument("--num-steps", type=int, default=64)
    parser.add_argument(
        "--keep",
        type=Path,
        help="write the datasets to DIR/<size>-<workers>w and keep them (e.g. for benchmarks/storage_codings.py); "
        "each must not exist yet",
    )
    parser.add_argument("--json", action="store_true", help="print one JSON document")
    parser.add_argument(
        "--storage",
        choices=["local", "s3"],
        default="local",
        help="s3: measure writes and loader reads on an S3 API server (moto, 127.0.0.1) against a local folder, "
        "with --levels-per-batch trajectories per batch, --batches-per-shard batches, --window-steps, --prefetch",
    )
    parser.add_argument("--window-steps", type=int, default=256, help="--storage s3: steps per trajectory")
    parser.add_argument("--prefetch", type=int, default=2, help="--storage s3: loader prefetch depth compared with 0")
    pipeline_cost.add_arguments(parser)
    args = parser.parse_args(argv)
    if args.cost:
        log = functools.partial(print, file=sys.stderr, flush=True) if args.json else print  # progress, figures
        with contextlib.ExitStack() as stack:
            scratch = args.keep or Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="kforge-cost-")))
            report = pipeline_cost.run_cost(args, scratch, log) | provenance() | {"machine": describe_machine()}
        if args.json:
            print(json.dumps(report, indent=1))
        return
    if args.storage == "s3":
        from benchmarks.object_storage import lines
        from benchmarks.object_storage import run as run_storage

        report = run_storage(
            args.sizes[0], args.levels_per_batch, args.batches_per_shard, args.window_steps, args.prefetch
        )
        report |= provenance() | {"machine": describe_machine()}
        print(json.dumps(report, indent=1) if args.json else "\n".join(lines(report)))
        return
    report = run(args, log=(lambda _: None) if args.json else print)
    if args.json:
        print(json.dumps(report, indent=1))
        return
    print("same data for every worker count:", report["same_data_across_worker_counts"])
    print("throughput relative to one worker:", report["throughput_vs_one_worker"])


if __name__ == "__main__":
    main()
