"""`kforge export --format kinetix <dataset> <out>`: write a dataset in another project's on-disk layout."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence

from pipeline.kinetix import DEFAULT_TRAJECTORIES_PER_SHARD, export_kinetix
from pipeline.storage import DatasetError

FORMATS = {"kinetix": export_kinetix}
"""Format name -> exporter(dataset_dir, out_dir, seed, trajectories_per_shard, show_progress)."""


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def main(argv: Sequence[str] | None = None, prog: str | None = None) -> None:
    """Export DATASET (a `kforge run` output directory) to OUT; `kinetix` writes OUT/<split> as Kinetix-Offline
    zarr v2 shards, readable by kinetix-env's TrajectoryDatasetManager. Exit 2 naming the problem on failure."""
    parser = argparse.ArgumentParser(prog=prog, description=main.__doc__)
    parser.add_argument("--format", required=True, choices=sorted(FORMATS), help="output layout")
    parser.add_argument("dataset", help="dataset: a directory (holds data/ and manifest/), s3:// or gs:// URL")
    parser.add_argument("out", help="output directory; the split is written to OUT/<split name>, which must be empty")
    parser.add_argument("--seed", type=int, default=0, help="seed of the trajectory shuffle across shards")
    parser.add_argument(
        "--trajectories-per-shard",
        type=_positive_int,
        default=DEFAULT_TRAJECTORIES_PER_SHARD,
        help="at most this many trajectories per shard (shards are filled evenly)",
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    try:
        summary = FORMATS[args.format](
            args.dataset,
            args.out,
            seed=args.seed,
            trajectories_per_shard=args.trajectories_per_shard,
            show_progress=not args.no_progress,
        )
    except DatasetError as error:
        print(f"error: {error}", file=sys.stderr)
        raise SystemExit(2) from error
    report = {
        "group": str(summary.group),
        "trajectories": summary.num_trajectories,
        "shards": summary.shard_sizes,
        "record_bytes": summary.record_bytes,
    }
    print(json.dumps(report, indent=1))
