"""`kforge stats DATASET [--out DIR]`: write a dataset card (markdown, a shard table and PNG plots)."""

from __future__ import annotations

import argparse
from collections.abc import Sequence

from kforge.pipeline.cli import add_common_options, fail, require_dataset


def main(argv: Sequence[str] | None = None, prog: str | None = None) -> None:
    """Write a dataset card: level counts (sampled, filtered by reason, trained, solved, kept, failed), bytes on
    disk, the data fingerprint and key config values, wall times per phase, and PNG plots (outcomes, expert success
    rates, episode lengths, training curves)."""
    parser = argparse.ArgumentParser(prog=prog, description=main.__doc__)
    parser.add_argument("dataset", help="dataset: a directory (holds data/ and manifest/), s3:// or gs:// URL")
    parser.add_argument("--out", help="folder or URL for card.md and card/*.png (default: DATASET)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar while reading commit records")
    args = add_common_options(parser).parse_args(argv)
    require_dataset(args.dataset)

    from kforge.pipeline.reading import collect_stats, write_card
    from kforge.pipeline.storage import DatasetError

    try:
        stats = collect_stats(args.dataset, show_progress=not args.no_progress)
    except DatasetError as error:
        if args.debug:
            raise
        raise fail(error) from error
    print(write_card(stats, args.out or args.dataset))
