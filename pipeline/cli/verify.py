"""`kforge verify DATASET [--repair]`: check every shard of a dataset against its commit records and name each bad
shard; `--repair` withdraws the commits of the bad level batches so that the next `kforge run` regenerates them."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from kforge.pipeline.cli import EXIT_DATA, add_common_options, fail, require_dataset


def main(argv: Sequence[str] | None = None, prog: str | None = None) -> None:
    """Check every committed level batch of DATASET: files against their checksums, decoded content against the
    records, finite kept trajectories whose episodes end in success; exit 1 naming each bad shard. With --repair,
    withdraw the commit of every bad level batch (saying which and why) so that re-running the job regenerates
    exactly those batches."""
    parser = argparse.ArgumentParser(prog=prog, description=main.__doc__)
    parser.add_argument("dir", help="dataset: a directory (holds data/ and manifest/), s3:// or gs:// URL")
    parser.add_argument(
        "--allow-incomplete", action="store_true", help="uncommitted level batches are notes, not problems"
    )
    parser.add_argument(
        "--repair",
        action="store_true",
        help="withdraw the commits of level batches that fail (implies --allow-incomplete); then re-run the job",
    )
    args = add_common_options(parser).parse_args(argv)
    require_dataset(args.dir)

    from kforge.pipeline.storage import CONFIG_FILE, DatasetError, format_report, join, open_dataset, verify_dataset

    rerun = f"kforge run {join(args.dir, CONFIG_FILE)}"
    try:
        reports = verify_dataset(args.dir, allow_incomplete=args.allow_incomplete or args.repair)
        batches_per_shard = open_dataset(args.dir).geometry.batches_per_shard
    except DatasetError as error:
        raise fail(error) from error
    print(format_report(reports))
    if args.repair:
        _repair(args.dir, reports, rerun)
        return
    bad = _report_bad_shards(args.dir, reports, rerun)
    uncommitted = sum(batches_per_shard - len(report.committed) for report in reports)
    if uncommitted and not args.allow_incomplete:
        print(
            f"{uncommitted} level batches are not committed: finish the job with {rerun}, or check only what is "
            "committed with --allow-incomplete",
            file=sys.stderr,
        )
    if bad:
        raise SystemExit(EXIT_DATA)


def _repair(dataset: str, reports: list, rerun: str) -> None:
    """Withdraw the commits of the bad level batches, saying which and what to run next."""
    from kforge.pipeline.storage import withdraw_bad_batches

    withdrawn = withdraw_bad_batches(dataset, reports)
    for withdrawal in withdrawn:
        print(f"withdrew the commit of {withdrawal.describe()}")
    if withdrawn:
        print(f"repaired: {len(withdrawn)} level batches to regenerate; next: {rerun}")
    else:
        print("nothing to repair")


def _report_bad_shards(dataset: str, reports: list, rerun: str) -> list[str]:
    """The bad shards' names, said on stderr with how to regenerate their bad level batches."""
    from kforge.pipeline.storage import shard_name

    bad = [shard_name(report.shard) for report in reports if not report.ok]
    if bad:
        print(f"verify failed: bad shards {', '.join(bad)}", file=sys.stderr)
        if any(report.bad_batches for report in reports):
            print(
                f"to regenerate the bad level batches: kforge verify --repair {dataset}, then {rerun}", file=sys.stderr
            )
    return bad
