"""Writing a level batch: checks, stored arrays, data files first and the commit record last; resume cleanup."""

from __future__ import annotations

import dataclasses
import hashlib
import math
import os
from collections.abc import Sequence

import jax
import numpy as np

from kforge.env import EnvState, action_mask
from kforge.pipeline.storage.layout import (
    ACTION,
    ACTION_MASK,
    DONE,
    EPISODE_LENGTHS,
    EXPERT_SUCCESS_RATE,
    LEVEL_ID,
    LEVEL_SEED,
    NUM_EPISODES,
    SUCCESS,
    VALID,
    DatasetError,
    Layout,
    flatten_state,
    unflatten_state,
)
from kforge.pipeline.storage.lease import require_lease
from kforge.pipeline.storage.manifest import (
    commit_record,
    committed_batches,
    record_exists,
    remove_record,
    shard_name,
    temp_records,
    write_record,
)
from kforge.pipeline.storage.records import ArrayEntry, BatchRecord, LevelRecord, Outcome
from kforge.pipeline.storage.shard_store import Dataset, array_digest, open_dataset
from kforge.pipeline.storage.store import Store, open_store


@dataclasses.dataclass(frozen=True)
class BatchTrajectories:
    """What the generator produced for one level batch of L levels, each with a T-step window.

    Rows of levels that are not kept may hold anything; only kept rows are stored, and every level's outcome goes
    to the commit record.
    """

    states: EnvState  # leaves (L, T, ...): the state before each action
    action: np.ndarray  # (L, T, *action shape) the action taken in that state
    done: np.ndarray  # (L, T) bool: the episode ended with that action (the next state is the level's start)
    success: np.ndarray  # (L, T) bool: ended with success (only where done)
    kept: np.ndarray  # (L,) bool: the trajectory is stored
    level_id: np.ndarray  # (L,) int: the level's index in its split
    level_seed: np.ndarray  # (L,) int: the seed the level was sampled from
    expert_success_rate: np.ndarray  # (L,) f32 [-] success rate of the level's expert in evaluation
    outcome: Sequence[str]  # (L,) Outcome.KEPT, or why the level was not kept (e.g. "filtered:trivial", "unsolved")
    expert_env_steps: np.ndarray | None = None  # (L,) int: env steps the selected expert had trained for
    trained_env_steps: np.ndarray | None = None  # (L,) int: env steps each level's training used
    budget_mode: str | None = None  # how experts trained: "fixed" / "streamed" (the whole budget) or "adaptive"
    curves: LearningCurves | None = None  # the experts' training curves, for dataset cards
    seconds: dict[str, float] = dataclasses.field(default_factory=dict)  # wall time per phase (not data)


@dataclasses.dataclass(frozen=True)
class LearningCurves:
    """Training curves of a level batch's experts, averaged over consecutive updates into at most a few points."""

    env_steps: np.ndarray  # (C,) int: env steps per level trained at the end of each point's updates
    success_rate: np.ndarray  # (L, C) f32 [-] share of episodes ending in success (NaN where none ended)
    mean_return: np.ndarray  # (L, C) f32 undiscounted episode return (NaN where no episode ended)


MAX_CURVE_POINTS = 32
"""Points per learning curve in a commit record (the release trains up to 5,000 updates per level)."""


def learning_curves(success_rate: np.ndarray, mean_return: np.ndarray, steps_per_update: int) -> LearningCurves:
    """Per-update (L, U) curves averaged over at most `MAX_CURVE_POINTS` runs of consecutive updates."""
    num_updates = success_rate.shape[1]
    groups = np.array_split(np.arange(num_updates), min(num_updates, MAX_CURVE_POINTS))

    def averaged(values: np.ndarray) -> np.ndarray:
        columns = []
        for group in groups:
            chunk = values[:, group]
            seen = np.isfinite(chunk)
            total = np.where(seen, chunk, 0.0).sum(axis=1)
            columns.append(np.where(seen.any(axis=1), total / np.maximum(seen.sum(axis=1), 1), np.nan))
        return np.stack(columns, axis=1).astype(np.float32)

    env_steps = np.array([(group[-1] + 1) * steps_per_update for group in groups], np.int64)
    return LearningCurves(env_steps, averaged(success_rate), averaged(mean_return))


def episode_lengths(done: np.ndarray) -> np.ndarray:
    """Lengths of the completed episodes of a (T,) done sequence that starts at an episode start."""
    ends = np.flatnonzero(done)
    return np.diff(np.concatenate([[-1], ends])).astype(np.int32)


def _bits(array: np.ndarray) -> np.ndarray:
    """An integer view of an array for exact comparison (NaN equals NaN, -0.0 differs from 0.0)."""
    if array.dtype.kind == "f":
        return array.view(f"u{array.dtype.itemsize}")
    return array


def _check_shape(name: str, value: np.ndarray, shape: tuple[int, ...], dtype) -> np.ndarray:
    value = np.asarray(value)
    if value.shape != shape or value.dtype != np.dtype(dtype):
        raise DatasetError(f"{name}: expected {np.dtype(dtype)}{shape}, got {value.dtype}{value.shape}")
    return value


def stored_arrays(layout: Layout, levels_per_batch: int, result: BatchTrajectories) -> dict[str, np.ndarray]:
    """Field name -> (L, ...) array to store for a level batch; empty (fill) rows for levels not kept.

    Raises `DatasetError` naming the field or level if the result does not fit the layout, a kept trajectory has no
    successful episode end or an unsuccessful one, holds non-finite values, or a per-level leaf changes over time.
    """
    size, steps = levels_per_batch, layout.num_steps
    kept = _check_shape("kept", result.kept, (size,), bool)
    if len(result.outcome) != size:
        raise DatasetError(f"outcome: expected {size} entries, got {len(result.outcome)}")
    for level in range(size):
        if bool(kept[level]) != (result.outcome[level] == Outcome.KEPT):
            raise DatasetError(f"level {level}: kept={bool(kept[level])} but outcome {result.outcome[level]!r}")
    done = _check_shape(DONE, result.done, (size, steps), bool)
    success = _check_shape(SUCCESS, result.success, (size, steps), bool)
    per_level = {
        LEVEL_ID: np.asarray(result.level_id).astype(np.int64),
        LEVEL_SEED: np.asarray(result.level_seed).astype(np.int64),
        EXPERT_SUCCESS_RATE: np.asarray(result.expert_success_rate).astype(np.float32),
    }
    for name, value in per_level.items():
        _check_shape(name, value, (size,), value.dtype)
    given = {ACTION: np.asarray(result.action), DONE: done, SUCCESS: success, **flatten_state(result.states)}
    for spec in layout.fields:
        if spec.name in given:  # every given field has a time axis, per-level state leaves included
            _check_shape(spec.name, given[spec.name], (size, steps) + spec.shape, spec.dtype)
    for level in np.flatnonzero(kept):
        _check_kept(level, done[level], success[level], given, layout)

    start = {spec.name: given[spec.name][:, 0] for spec in layout.state_fields}
    masks = np.asarray(jax.vmap(action_mask)(unflatten_state(layout, start)))
    first = {spec.name: start[spec.name] for spec in layout.state_fields if not spec.per_step}
    num_episodes = done.sum(axis=1).astype(np.int32)
    lengths = np.zeros((size, steps), np.int32)
    for level in range(size):
        found = episode_lengths(done[level])
        lengths[level, : len(found)] = found
    values = {**given, **first, **per_level}
    values |= {ACTION_MASK: masks, VALID: kept, NUM_EPISODES: num_episodes, EPISODE_LENGTHS: lengths}
    arrays = {}
    for spec in layout.fields:
        value = values[spec.name]
        arrays[spec.name] = np.where(kept.reshape((size,) + (1,) * (value.ndim - 1)), value, spec.fill_value).astype(
            spec.dtype
        )
    return arrays


def _check_kept(level: int, done: np.ndarray, success: np.ndarray, given: dict, layout: Layout) -> None:
    ends = np.flatnonzero(done)
    if len(ends) == 0:
        raise DatasetError(f"level {level}: kept but no episode ends within the window")
    failed = np.flatnonzero(done & ~success)
    if len(failed):
        raise DatasetError(f"level {level}: kept but episodes ending at steps {failed.tolist()} are not successes")
    stray = np.flatnonzero(success & ~done)
    if len(stray):
        raise DatasetError(f"level {level}: success flagged without an episode end at steps {stray.tolist()}")
    for spec in layout.fields:
        if spec.name not in given:
            continue
        value = given[spec.name][level]
        if value.dtype.kind == "f" and not np.all(np.isfinite(value)):
            raise DatasetError(f"level {level}: {spec.name} holds non-finite values")
        if spec.name.startswith("env_state/") and not spec.per_step:
            changed = np.flatnonzero(np.any((_bits(value) != _bits(value[:1])).reshape(len(value), -1), axis=1))
            if len(changed):
                raise DatasetError(
                    f"level {level}: per-level field {spec.name} changes within the window (first at step "
                    f"{changed[0]}); it must be listed in layout.DYNAMIC_STATE_FIELDS"
                )


def _json_number(value) -> float | None:
    value = float(value)
    return value if math.isfinite(value) else None


def write_level_batch(dataset: Dataset, shard: int, batch: int, result: BatchTrajectories) -> dict:
    """Store and commit level batch `batch` of `shard`; returns its commit record."""
    remove_record(dataset.root, shard, batch)
    record = stage_level_batch(dataset, shard, batch, result)
    return write_record(dataset.root, shard, batch, record)


def stage_level_batch(
    dataset: Dataset, shard: int, batch: int, result: BatchTrajectories, job_id: str | None = None
) -> dict:
    """Write the data files of level batch `batch` of `shard` and return the record that commits them.

    Order: check, refuse a committed batch (`DatasetError`: a committed batch's files are never rewritten, so a
    writer that lost its shard or lease cannot change a commit of another), mark the batch as staged by job
    `job_id` (`staging_key`; None: an unleased writer, e.g. a test, marks nothing), write the data files (each
    replaced atomically by tensorstore). The batch counts as committed only once the returned record is written
    (`manifest.commit_record`, by the coordinator); rerunning after any interruption overwrites the same files.
    """
    geometry, layout = dataset.geometry, dataset.layout
    global_batch = geometry.global_batch(shard, batch)
    arrays = stored_arrays(layout, geometry.levels_per_batch, result)
    if record_exists(dataset.store, shard, batch):
        raise DatasetError(f"{shard_name(shard)} batch {batch}: already committed; its files are not rewritten")
    if job_id is not None:
        dataset.store.write(staging_key(shard, batch, job_id), b"")
    dataset.write_batch(global_batch, arrays)

    files = {}
    for name, value in arrays.items():
        key = dataset.batch_key(name, global_batch)
        data = dataset.store.read(key)
        if data is None:
            files[name] = ArrayEntry(None, None, array_digest(value))
        else:
            files[name] = ArrayEntry(key, hashlib.sha256(data).hexdigest(), array_digest(value), len(data))
    slots = geometry.slots(shard, batch)
    curves = result.curves
    levels = tuple(
        LevelRecord(
            slot=slot,
            outcome=Outcome(result.outcome[i]),
            level_id=int(result.level_id[i]),
            level_seed=int(result.level_seed[i]),
            expert_success_rate=_json_number(result.expert_success_rate[i]),
            episode_lengths=tuple(episode_lengths(np.asarray(result.done[i])).tolist()),
            expert_env_steps=None if result.expert_env_steps is None else int(result.expert_env_steps[i]),
            trained_env_steps=None if result.trained_env_steps is None else int(result.trained_env_steps[i]),
            curve_success_rate=None if curves is None else tuple(_json_number(v) for v in curves.success_rate[i]),
            curve_mean_return=None if curves is None else tuple(_json_number(v) for v in curves.mean_return[i]),
        )
        for i, slot in enumerate(slots)
    )
    record = BatchRecord(
        shard=shard,
        batch=batch,
        global_batch=global_batch,
        slots=(slots.start, slots.stop),
        num_kept=int(arrays[VALID].sum()),
        levels=levels,
        arrays=files,
        curve_env_steps=None if curves is None else tuple(curves.env_steps.tolist()),
        budget_mode=result.budget_mode,
        provenance={"seconds": dict(result.seconds)} if result.seconds else None,
    )
    return record.to_json()


STAGING_DIR = "staging"
"""Prefix of the staging markers: `staging/shard-000012/batch-003/<job id>`, an empty object per job that wrote
data files of an uncommitted level batch (`stage_level_batch`)."""


def staging_key(shard: int, batch: int, job_id: str) -> str:
    """The key of job `job_id`'s staging marker of a level batch."""
    return f"{_batch_staging_prefix(shard, batch)}{job_id}"


def _batch_staging_prefix(shard: int, batch: int) -> str:
    return f"{STAGING_DIR}/{shard_name(shard)}/batch-{batch:03d}/"


def staged_by(root: str | os.PathLike | Store, shard: int) -> dict[int, set[str]]:
    """Batch -> the jobs whose staging markers it has, for each level batch of `shard` with one."""
    store = open_store(root)
    prefix = f"{STAGING_DIR}/{shard_name(shard)}/"
    found: dict[int, set[str]] = {}
    for key in store.list(prefix):
        batch, _, job_id = key.removeprefix(prefix).partition("/")
        if batch.startswith("batch-") and job_id:
            found.setdefault(int(batch.removeprefix("batch-")), set()).add(job_id)
    return found


def unmark_committed(root: str | os.PathLike | Store, shard: int, batch: int) -> None:
    """Remove every staging marker of a committed level batch (its files are the commit's now)."""
    store = open_store(root)
    for key in store.list(_batch_staging_prefix(shard, batch)):
        store.delete(key)


class ShardWriter:
    """The single writer of one shard under job `job_id`'s lease: it starts by removing what a crash left in the
    shard (`clean_uncommitted`, `LeaseLost` if the job does not hold the lease with a heartbeat at most
    `max_lease_age_s` old), then stages level batches (`stage`) and, once the coordinator committed a batch's record,
    drops its staging markers (`committed`)."""

    def __init__(self, root: str | os.PathLike | Store, shard: int, job_id: str, max_lease_age_s: float | None = None):
        self._dataset = open_dataset(root)
        self._shard, self._job_id = shard, job_id
        clean_uncommitted(self._dataset.store, shard, job_id, max_lease_age_s)

    def stage(self, batch: int, result: BatchTrajectories) -> dict:
        """Write the batch's data files and return the record that commits them (`stage_level_batch`)."""
        return stage_level_batch(self._dataset, self._shard, batch, result, self._job_id)

    def committed(self, batch: int) -> None:
        """The batch's record is committed: its files are the commit's now (`unmark_committed`)."""
        unmark_committed(self._dataset.store, self._shard, batch)


def commit_level_batch(
    root: str | os.PathLike | Store,
    shard: int,
    batch: int,
    record: dict,
    job_id: str | None = None,
    max_lease_age_s: float | None = None,
) -> dict | None:
    """Commit a level batch whose files a `ShardWriter` staged: with `job_id`, only while that job holds the
    dataset's lease with a heartbeat at most `max_lease_age_s` old (`LeaseLost` otherwise), and only if the batch is
    not committed yet (`commit_record`). Returns the record as stored, or None if one exists."""
    if job_id is not None:
        require_lease(root, job_id, max_lease_age_s)
    return commit_record(root, shard, batch, record)


def clean_uncommitted(
    root: str | os.PathLike | Store, shard: int, job_id: str, max_lease_age_s: float | None = None
) -> list[str]:
    """Remove what a crash of this job left in `shard`: data objects of level batches without a record, half-done
    local writes (tensorstore lock files), half-written records and staging markers. Returns the removed keys.

    Only the data of batches that no other job marked as staged is removed (`staging_key`): a job that lost the
    lease may still be writing its batches, and their files stay until this job stages the batch itself (the same
    bytes: the data is a function of the config) and commits it. Only the shard's single writer may call it, under
    its job's lease (`LeaseLost` if job `job_id` does not hold the dataset's lease, or its heartbeat is older than
    `max_lease_age_s`).
    """
    dataset = open_dataset(root)
    require_lease(dataset.store, job_id, max_lease_age_s)
    store = dataset.store
    committed = set(committed_batches(store, shard))
    staged = staged_by(store, shard)
    removed = list(temp_records(store, shard))
    partial = []
    for batch in range(dataset.geometry.batches_per_shard):
        stagers = staged.get(batch, set())
        if batch not in committed and stagers - {job_id}:
            continue  # another job's staged files: not this job's to remove
        keys = [
            dataset.batch_key(spec.name, dataset.geometry.global_batch(shard, batch)) for spec in dataset.layout.fields
        ]
        partial += [found for key in keys for found in store.partial_writes(key)]
        if batch not in committed:
            removed += [key for key in keys if key in store.list(key)]
        removed += [staging_key(shard, batch, stager) for stager in sorted(stagers)]
    for key in removed:
        store.delete(key)
    for key in partial:
        store.delete_partial(key)
    return sorted(removed + partial)
