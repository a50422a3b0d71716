"""Repair of a damaged dataset: the commits of level batches that fail verification are withdrawn, so the next run
regenerates exactly those batches (generation is deterministic, so the repaired dataset equals an undamaged one).

Also the check a resumed run makes before it trusts its commits: every committed batch's record reads and every
data file it names exists with its recorded checksum.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
from collections.abc import Sequence

from kforge.pipeline.storage.layout import DatasetError
from kforge.pipeline.storage.manifest import committed_batches, read_record, remove_record, shard_name
from kforge.pipeline.storage.shard_store import CONFIG_FILE, DATA_DIR, object_digest, open_dataset
from kforge.pipeline.storage.store import Location, Store, join
from kforge.pipeline.storage.verify import ShardReport

HASH_THREADS = 4
"""Objects read and hashed at once by `damaged_commits` (I/O and hashlib release the GIL)."""


class DatasetDamaged(DatasetError):
    """Committed level batches of a dataset have missing, unreadable or damaged files."""


@dataclasses.dataclass(frozen=True)
class Withdrawal:
    """A level batch whose commit was withdrawn, and why."""

    shard: int
    batch: int
    problems: tuple[str, ...]

    def describe(self) -> str:
        """ "shard-000001 batch 0: <problem>; <problem>"."""
        where = f"{shard_name(self.shard)} batch {self.batch}"
        return f"{where}: {'; '.join(problem.removeprefix(f'{where}: ') for problem in self.problems)}"


def withdraw_commit(root: Location, shard: int, batch: int) -> bool:
    """Withdraw a level batch's commit (remove its record), so that the next run regenerates the batch; True if it
    was committed."""
    return remove_record(root, shard, batch)


def withdraw_bad_batches(root: Location, reports: Sequence[ShardReport]) -> list[Withdrawal]:
    """Withdraw the commit of every level batch the reports (`verify_dataset`) found bad; returns what was withdrawn.

    Only commit records are removed (one object each); the batches' data objects are left for the next run,
    which removes them before it regenerates the batches (`clean_uncommitted`).
    """
    withdrawn = []
    for report in reports:
        for batch, problems in sorted(report.bad_batches.items()):
            withdraw_commit(root, report.shard, batch)
            withdrawn.append(Withdrawal(report.shard, batch, tuple(problems)))
    return withdrawn


def damaged_commits(root: Location, read_objects: bool = True) -> list[str]:
    """Committed level batches whose record does not read, or whose recorded data files are missing or differ from
    their recorded sha256 (a flipped byte), one line each ("shard-000001 batch 1: file data/done/c/3/0 missing");
    empty for an intact dataset. Reads every data object once (in parallel); with `read_objects=False` only the
    records and one listing of the data objects (missing files, not their bytes). Decoding and content checks are
    `kforge verify`'s."""
    dataset = open_dataset(root)
    geometry = dataset.geometry
    damaged, expected = [], []
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
            arrays = record.arrays
            missing = [spec.name for spec in dataset.layout.fields if spec.name not in arrays]
            if missing:
                damaged.append(f"{where}: {missing[0]} not in the record")
                continue
            global_batch = geometry.global_batch(shard, batch)
            for spec in dataset.layout.fields:
                if arrays[spec.name].sha256 is not None:
                    expected.append((where, dataset.batch_key(spec.name, global_batch), arrays[spec.name].sha256))
    if read_objects:
        with concurrent.futures.ThreadPoolExecutor(HASH_THREADS) as pool:
            digests = list(pool.map(lambda key: object_digest(dataset.store, key), [key for _, key, _ in expected]))
    else:
        present = set(dataset.store.list(f"{DATA_DIR}/"))
        digests = [recorded if key in present else None for _, key, recorded in expected]
    bad_batches = set()
    for (where, key, recorded), digest in zip(expected, digests, strict=True):
        if digest != recorded and where not in bad_batches:
            bad_batches.add(where)
            what = "missing" if digest is None else "sha256 mismatch"
            damaged.append(f"{where}: file {key} {what}")
    return damaged


def require_intact(root: Location, then: str | None = None, read_objects: bool = True) -> None:
    """Raise `DatasetDamaged` (one line: how many batches, the first problem, the command that repairs them, then
    `then`, by default the run that regenerates them) unless every committed level batch's record reads and its data
    files exist with their recorded sha256 (`damaged_commits`; with `read_objects=False` their existence only). What
    the readers that export or learn from a dataset (`kforge export`, `kforge bc train`) check before they read, and,
    without reading objects, what a job checks before it resumes."""
    damaged = damaged_commits(root, read_objects)
    if damaged:
        location = root.location if isinstance(root, Store) else str(root)
        then = then or f"`kforge run {join(location, CONFIG_FILE)}` to regenerate them"
        raise DatasetDamaged(
            f"{location}: {len(damaged)} committed level batches have missing, unreadable or damaged files "
            f"({damaged[0]}); run `kforge verify --repair {location}`, then {then}"
        )
