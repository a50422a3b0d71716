"""Verification of a dataset (`kforge verify`): every shard checked against its commit records, each bad one named.

Per committed level batch: the data files exist and match their recorded sha256, decode (crc32c on every chunk),
match the recorded content digests, and hold what the record says (kept levels, ids, seeds, episode lengths); kept
trajectories are finite, their episode ends are all successes (at least one), their timestep counter restarts after
each end; empty slots hold only fill values. Shards with uncommitted level batches are incomplete.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Sequence

import numpy as np

from kforge.pipeline.storage.layout import (
    DONE,
    EPISODE_LENGTHS,
    LEVEL_ID,
    LEVEL_SEED,
    NUM_EPISODES,
    STATE_PREFIX,
    SUCCESS,
    VALID,
    DatasetError,
)
from kforge.pipeline.storage.manifest import committed_batches, read_record, shard_name, temp_records
from kforge.pipeline.storage.records import BatchRecord
from kforge.pipeline.storage.shard_store import Dataset, array_digest, object_digest, open_dataset
from kforge.pipeline.storage.writer import episode_lengths

TIMESTEP = f"{STATE_PREFIX}/timestep"


@dataclasses.dataclass
class ShardReport:
    """What verification found in one shard."""

    shard: int
    committed: list[int]
    num_kept: int = 0
    problems: list[str] = dataclasses.field(default_factory=list)
    notes: list[str] = dataclasses.field(default_factory=list)
    bad_batches: dict[int, list[str]] = dataclasses.field(default_factory=dict)  # committed batch -> its problems

    @property
    def ok(self) -> bool:
        return not self.problems


def verify_dataset(root: str | os.PathLike, allow_incomplete: bool = False) -> list[ShardReport]:
    """One report per shard of the dataset; raises `DatasetError` if the dataset itself cannot be opened."""
    dataset = open_dataset(root)
    return [verify_shard(dataset, shard, allow_incomplete) for shard in range(dataset.geometry.num_shards)]


def verify_shard(dataset: Dataset, shard: int, allow_incomplete: bool = False) -> ShardReport:
    """Check every committed level batch of `shard`; see the module docstring."""
    geometry = dataset.geometry
    report = ShardReport(shard, committed_batches(dataset.store, shard))
    missing = [b for b in range(geometry.batches_per_shard) if b not in report.committed]
    if missing:
        message = f"level batches {missing} not committed"
        (report.notes if allow_incomplete else report.problems).append(message)
    store = dataset.store
    for key in temp_records(store, shard):
        report.notes.append(f"half-written record {key.rsplit('/', 1)[-1]} (removed on resume)")
    for batch in range(geometry.batches_per_shard):
        global_batch = geometry.global_batch(shard, batch)
        for spec in dataset.layout.fields:
            key = dataset.batch_key(spec.name, global_batch)
            if batch not in report.committed and key in store.list(key):
                report.notes.append(f"batch {batch}: uncommitted data file {key}")
            if store.partial_writes(key):
                report.notes.append(f"batch {batch}: stale lock file beside {key}")
    for batch in report.committed:
        if batch >= geometry.batches_per_shard:  # a record past the geometry: withdrawn by --repair
            problem = f"record outside the dataset's {geometry.batches_per_shard} level batches per shard"
            report.problems.append(f"batch {batch}: {problem}")
            report.bad_batches[batch] = [problem]
            continue
        try:
            problems, num_kept = _verify_batch(dataset, shard, batch)
        except DatasetError as error:
            problems, num_kept = [str(error)], 0
        report.problems += [f"batch {batch}: {problem}" for problem in problems]
        report.num_kept += num_kept
        if problems:
            report.bad_batches[batch] = problems
    return report


def _verify_batch(dataset: Dataset, shard: int, batch: int) -> tuple[list[str], int]:
    record = read_record(dataset.store, shard, batch)
    layout, geometry = dataset.layout, dataset.geometry
    slots = geometry.slots(shard, batch)
    problems = []
    if record.slots != (slots.start, slots.stop) or len(record.levels) != len(slots):
        return [f"record slots {list(record.slots)} do not match the dataset geometry {[slots.start, slots.stop]}"], 0
    files = record.arrays
    arrays = {}
    for spec in layout.fields:
        entry = files.get(spec.name)
        if entry is None:
            problems.append(f"{spec.name}: not in the record")
            continue
        key = dataset.batch_key(spec.name, geometry.global_batch(shard, batch))
        digest = object_digest(dataset.store, key)
        if digest != entry.sha256:
            what = "missing" if digest is None else ("unexpected" if entry.sha256 is None else "sha256 mismatch")
            problems.append(f"{spec.name}: file {key} {what}")
        try:
            arrays[spec.name] = dataset.read([spec.name], slots)[spec.name]
        except ValueError as error:
            problems.append(f"{spec.name}: cannot decode ({error})")
            continue
        if array_digest(arrays[spec.name]) != entry.data_sha256:
            problems.append(f"{spec.name}: decoded content differs from the record")
    if problems:
        return problems, 0
    return _check_content(layout, record, arrays), int(arrays[VALID].sum())


def _check_content(layout, record: BatchRecord, arrays: dict[str, np.ndarray]) -> list[str]:
    problems = []
    levels = record.levels
    kept = arrays[VALID]
    recorded_kept = np.array([level.kept for level in levels])
    if not np.array_equal(kept, recorded_kept) or int(kept.sum()) != record.num_kept:
        problems.append(f"kept flags {kept.astype(int).tolist()} differ from the record's")
    for i, level in enumerate(levels):
        where = f"slot {level.slot}"
        if not kept[i]:
            for spec in layout.fields:
                fill = np.full_like(arrays[spec.name][i], spec.fill_value)
                if not np.array_equal(arrays[spec.name][i], fill, equal_nan=fill.dtype.kind == "f"):
                    problems.append(f"{where}: empty slot holds data in {spec.name}")
            continue
        for name, recorded in ((LEVEL_ID, level.level_id), (LEVEL_SEED, level.level_seed)):
            if int(arrays[name][i]) != recorded:
                problems.append(f"{where}: {name} {int(arrays[name][i])} but the record says {recorded}")
        for spec in layout.fields:
            value = arrays[spec.name][i]
            if value.dtype.kind == "f" and not np.all(np.isfinite(value)):
                problems.append(f"{where}: {spec.name} holds non-finite values")
        problems += [f"{where}: {problem}" for problem in _check_episodes(arrays, i, list(level.episode_lengths))]
    return problems


def _check_episodes(arrays: dict[str, np.ndarray], i: int, recorded_lengths: list[int]) -> list[str]:
    done, success = arrays[DONE][i], arrays[SUCCESS][i]
    problems = []
    if not done.any():
        problems.append("kept trajectory has no episode end")
    if (done & ~success).any():
        problems.append(f"episodes ending at steps {np.flatnonzero(done & ~success).tolist()} are not successes")
    if (success & ~done).any():
        problems.append(f"success without an episode end at steps {np.flatnonzero(success & ~done).tolist()}")
    lengths = episode_lengths(done)
    stored = arrays[EPISODE_LENGTHS][i]
    if lengths.tolist() != recorded_lengths or int(arrays[NUM_EPISODES][i]) != len(lengths):
        problems.append(f"episode lengths {lengths.tolist()} differ from the record or the episode count")
    elif stored[: len(lengths)].tolist() != lengths.tolist() or stored[len(lengths) :].any():
        problems.append(f"stored {EPISODE_LENGTHS} differ from the episode ends")
    timestep = arrays[TIMESTEP][i]
    expected = np.concatenate([[0], np.where(done[:-1], 0, timestep[:-1] + 1)])
    if timestep[0] != 0 or not np.array_equal(timestep, expected):
        problems.append("timestep does not count from 0 and restart after each episode end")
    return problems


def format_report(reports: Sequence[ShardReport]) -> str:
    """Human-readable report: one line per shard, then its problems and notes indented."""
    lines = []
    for report in reports:
        status = "ok" if report.ok else "BAD"
        batches = _count(len(report.committed), "level batch", "level batches")
        kept = _count(report.num_kept, "trajectory", "trajectories")
        lines.append(f"{shard_name(report.shard)}: {status} ({batches} committed, {kept})")
        lines += [f"  problem: {problem}" for problem in report.problems]
        lines += [f"  note: {note}" for note in report.notes]
    bad = [shard_name(report.shard) for report in reports if not report.ok]
    total = sum(report.num_kept for report in reports)
    lines.append(
        f"{_count(len(reports), 'shard', 'shards')}, {_count(total, 'trajectory', 'trajectories')} verified; "
        f"bad shards: {', '.join(bad) or 'none'}"
    )
    return "\n".join(lines)


def _count(number: int, singular: str, plural: str) -> str:
    return f"{number} {singular if number == 1 else plural}"
