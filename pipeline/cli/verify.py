"""`kforge verify DATASET`: check every shard of a dataset against its commit records and name each bad shard."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence


def main(argv: Sequence[str] | None = None, prog: str | None = None) -> None:
    """Check every committed level batch of DATASET: files against their checksums, decoded content against the
    records, finite kept trajectories whose episodes end in success; exit 1 naming each bad shard."""
    parser = argparse.ArgumentParser(prog=prog, description=main.__doc__)
    parser.add_argument("dir", help="dataset: a directory (holds data/ and manifest/), s3:// or gs:// URL")
    parser.add_argument(
        "--allow-incomplete", action="store_true", help="uncommitted level batches are notes, not problems"
    )
    args = parser.parse_args(argv)

    from pipeline.storage import DatasetError, format_report, shard_name, verify_dataset

    try:
        reports = verify_dataset(args.dir, allow_incomplete=args.allow_incomplete)
    except DatasetError as error:
        print(f"error: {error}", file=sys.stderr)
        raise SystemExit(1) from error
    print(format_report(reports))
    bad = [shard_name(report.shard) for report in reports if not report.ok]
    if bad:
        print(f"verify failed: bad shards {', '.join(bad)}", file=sys.stderr)
        raise SystemExit(1)
