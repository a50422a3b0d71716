"""Repair of a damaged dataset: the commits of level batches that fail verification are withdrawn, so the next run
regenerates exactly those batches (generation is deterministic, so the repaired dataset equals an undamaged one).

Also the cheap check a resumed run makes before it trusts its commits: every committed batch's record reads and
every data file it names exists (checksums are `kforge verify`'s job).
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Sequence

from pipeline.storage.layout import DatasetError
from pipeline.storage.manifest import committed_batches, read_record, remove_record, shard_name
from pipeline.storage.shard_store import open_dataset
from pipeline.storage.verify import ShardReport


@dataclasses.dataclass(frozen=True)
class Withdrawal:
    """A level batch whose commit was withdrawn, and why."""

    shard: int
    batch: int
    problems: tuple[str, ...]

    def describe(self) -> str:
        return f"{shard_name(self.shard)} batch {self.batch}: {'; '.join(self.problems)}"


def withdraw_commit(root: str | os.PathLike, shard: int, batch: int) -> bool:
    """Withdraw a level batch's commit (remove its record), so that the next run regenerates the batch; True if it
    was committed."""
    return remove_record(root, shard, batch)


def withdraw_bad_batches(root: str | os.PathLike, reports: Sequence[ShardReport]) -> list[Withdrawal]:
    """Withdraw the commit of every level batch the reports (`verify_dataset`) found bad; returns what was withdrawn.

    Only commit records are removed (atomically, one file each); the batches' data files are left for the next run,
    which removes them before it regenerates the batches (`clean_uncommitted`).
    """
    withdrawn = []
    for report in reports:
        for batch, problems in sorted(report.bad_batches.items()):
            withdraw_commit(root, report.shard, batch)
            withdrawn.append(Withdrawal(report.shard, batch, tuple(problems)))
    return withdrawn


def damaged_commits(root: str | os.PathLike) -> list[str]:
    """Committed level batches whose record does not read or whose recorded data files are missing, one line each
    ("shard-000001 batch 1: file data/done/c/3/0 missing"); empty for an intact dataset."""
    dataset = open_dataset(root)
    geometry = dataset.geometry
    damaged = []
    for shard in range(geometry.num_shards):
        for batch in committed_batches(root, shard):
            where = f"{shard_name(shard)} batch {batch}"
            try:
                record = read_record(root, shard, batch)
            except DatasetError as error:
                damaged.append(str(error))
                continue
            if batch >= geometry.batches_per_shard:
                damaged.append(f"{where}: outside the dataset's {geometry.batches_per_shard} batches per shard")
                continue
            global_batch = geometry.global_batch(shard, batch)
            for spec in dataset.layout.fields:
                entry = record.get("arrays", {}).get(spec.name)
                path = dataset.batch_file(spec.name, global_batch)
                if entry is None:
                    damaged.append(f"{where}: {spec.name} not in the record")
                    break
                if entry.get("sha256") is not None and not path.is_file():
                    damaged.append(f"{where}: file {path.relative_to(dataset.root)} missing")
                    break
    return damaged
