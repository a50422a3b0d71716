"""`kforge export --format kinetix <dataset> <out>`: write a dataset in another project's on-disk layout."""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence

from kforge.pipeline.cli import add_common_options, fail, require_dataset

READING_HINT = """How to read it:
  - with Kinetix: in a virtualenv of its own, pip install kinetix-env==3.0.2 (it brings zarr 2.18; the zarr 3 that
    kforge installs cannot open these zarr v2 structured records), then
    kinetix.data.data_utils.TrajectoryDatasetManager("{group}", batch_size=..., seed=0).load_next_batch()
  - with kforge: from kforge.pipeline.kinetix import load_kinetix_levels; load_kinetix_levels("{group}") gives each
    trajectory's level and initial state
See docs/kinetix-export.md."""
"""Printed after an export (and in docs/kinetix-export.md): how the Kinetix-format shards are read."""

FORMATS = ("kinetix",)
"""Formats `--format` takes (kinetix: pipeline.kinetix.export_kinetix)."""


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def main(argv: Sequence[str] | None = None, prog: str | None = None) -> None:
    """Export DATASET (a `kforge run` output directory) to OUT; `kinetix` writes OUT/<split> as Kinetix-Offline
    zarr v2 shards, readable by kinetix-env's TrajectoryDatasetManager (with zarr 2) and by
    pipeline.kinetix.load_kinetix_levels; prints how."""
    parser = argparse.ArgumentParser(prog=prog, description=main.__doc__)
    parser.add_argument("--format", required=True, choices=FORMATS, help="output layout")
    parser.add_argument("dataset", help="dataset: a directory (holds data/ and manifest/), s3:// or gs:// URL")
    parser.add_argument("out", help="output directory; the split is written to OUT/<split name>, which must be empty")
    parser.add_argument("--seed", type=int, default=0, help="seed of the trajectory shuffle across shards")
    parser.add_argument(
        "--trajectories-per-shard",
        type=_positive_int,
        help="at most this many trajectories per shard (shards are filled evenly; default Kinetix-Offline's)",
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--json", action="store_true", help="print the export summary as JSON (for scripts)")
    args = add_common_options(parser).parse_args(argv)
    require_dataset(args.dataset)

    from kforge.pipeline.kinetix import DEFAULT_TRAJECTORIES_PER_SHARD, export_kinetix
    from kforge.pipeline.storage import DatasetError

    try:
        summary = export_kinetix(
            args.dataset,
            args.out,
            seed=args.seed,
            trajectories_per_shard=args.trajectories_per_shard or DEFAULT_TRAJECTORIES_PER_SHARD,
            show_progress=not args.no_progress,
        )
    except DatasetError as error:
        if args.debug:
            raise
        raise fail(error) from error
    report = {
        "group": str(summary.group),
        "trajectories": summary.num_trajectories,
        "shards": summary.shard_sizes,
        "record_bytes": summary.record_bytes,
    }
    if args.json:
        print(json.dumps(report, indent=1))
        return
    print(
        f"wrote {summary.num_trajectories} trajectories in {len(summary.shard_sizes)} "
        f"{'shard' if len(summary.shard_sizes) == 1 else 'shards'} to {summary.group} "
        f"({summary.record_bytes} bytes per stored step)"
    )
    print(READING_HINT.format(group=summary.group))
