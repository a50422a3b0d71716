"""Batches of stored trajectories for users, with the interface of Kinetix's `TrajectoryDatasetManager`.

Only committed, kept trajectories are read. Order: each epoch is a permutation of all trajectories drawn from
(seed, epoch); data-parallel reader r of R takes every R-th entry of it starting at r (so readers are disjoint and
together cover the epoch, up to the remainder that R does not divide); its batches are consecutive runs of its part,
and the last incomplete batch of an epoch is dropped (it differs from epoch to epoch).
"""

from __future__ import annotations

import collections
import itertools
import os
from collections.abc import Callable, Collection, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from kforge.env import EnvState, StaticEnvParams
from kforge.pipeline.storage import (
    ACTION,
    ACTION_MASK,
    DATA_DIR,
    DONE,
    VALID,
    BatchRecord,
    DatasetError,
    iter_records,
    open_dataset,
    shard_name,
    unflatten_state,
)

WHOLE_OBJECT_BYTES = 1_000_000
"""[bytes] On an object store, a per-step field's shard object up to this size is read whole and the batch's
trajectories picked from it, rather than by one range request per trajectory plus one for the object's index. A
request to S3 or GCS costs a round trip of about 10-30 ms, in which one stream transfers about 1 MB, so reading the
rest of a small object costs less than the requests it saves. Per-level fields (one chunk per object) take one request
either way; a local folder is always read trajectory by trajectory (there are no round trips to save)."""


class ActionEnvStateMask(NamedTuple):
    """One batch (Kinetix's `ActionEnvStateMask` plus the rendered observation and the trajectories' slots)."""

    action: jnp.ndarray  # (B, T, *action shape)
    env_state: EnvState  # leaves (B, T, ...); per-level leaves broadcast over time
    mask: jnp.ndarray  # (B, T) bool, all True (every stored step is real)
    action_mask: jnp.ndarray  # (B, T, 6) bool, the level's mask broadcast over time
    done: jnp.ndarray  # (B, T) bool
    obs: Any  # render_fn(env_state) with leading (B, T), or None without a render_fn
    trajectory_index: np.ndarray  # (B,) global slot of each trajectory in the dataset


def _wanted(level, wanted: set[int] | None) -> bool:
    """A level's trajectory is read: kept, and of a selected level (all levels without a selection)."""
    return level.kept and (wanted is None or level.level_id in wanted)


class TrajectoryDatasetManager:
    """Endless deterministic batches of (B, T, ...) trajectories from a dataset directory.

    `render_fn(env_state) -> observation` of one state (e.g. `lambda s: env.observe(s, static, type)`) is applied
    to every step of a batch, compiled once. With `prefetch=k`, a background thread reads, decodes and puts on the
    device the next k batches while the caller works on the current one (same batches, same order). `level_ids`
    restricts the reader to the trajectories of those levels (e.g. a training set without its validation levels);
    `start_batch=n` starts at this reader's n-th batch, as if n batches had been loaded (a resumed learner
    continues its sequence).
    On an object store, shard objects up to `whole_object_bytes` are read whole (`WHOLE_OBJECT_BYTES`; 0: every
    trajectory by its own range requests); the batches are the same either way. With `cache_bytes`, the reader's
    trajectories are read once into host memory when their decoded size fits (`cached` says whether they did), and
    batches are gathered from there: the same batches, without storage reads.
    The reader fails closed: opening it checks that every object the commit records name for the fields it reads
    exists (and, in a local folder, has its recorded size), so a lost object is a `DatasetError` naming its level
    batch and array rather than fill values; a read that does not decode names them too.
    """

    def __init__(
        self,
        dataset_dir: str | os.PathLike,
        batch_size: int,
        seed: int = 42,
        shard_index: int = 0,
        total_shard_count: int = 1,
        render_fn: Callable[[EnvState], Any] | None = None,
        static_env_params: StaticEnvParams | None = None,
        prefetch: int = 0,
        level_ids: Collection[int] | None = None,
        start_batch: int = 0,
        whole_object_bytes: int = WHOLE_OBJECT_BYTES,
        cache_bytes: int = 0,
    ):
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        if prefetch < 0:
            raise ValueError(f"prefetch must be >= 0, got {prefetch}")
        if start_batch < 0:
            raise ValueError(f"start_batch must be >= 0, got {start_batch}")
        if not 0 <= shard_index < total_shard_count:
            raise ValueError(f"shard_index {shard_index} out of range [0, {total_shard_count})")
        self.dataset = open_dataset(dataset_dir)
        if static_env_params is not None and static_env_params != self.dataset.layout.static:
            raise DatasetError(
                f"{dataset_dir}: stored with {self.dataset.layout.static}, but {static_env_params} was requested"
            )
        self.batch_size, self.seed = batch_size, seed
        self.shard_index, self.total_shard_count = shard_index, total_shard_count
        wanted = None if level_ids is None else {int(level) for level in level_ids}
        records = list(iter_records(self.dataset.store))
        self.slots = np.array(
            sorted(level.slot for record in records for level in record.levels if _wanted(level, wanted)), np.int64
        )
        self._check_objects([record for record in records if self._holds_wanted(record, wanted)])
        self._whole = self._whole_objects(records, whole_object_bytes)
        self.length = len(self.slots) // total_shard_count
        """Trajectories this reader sees per epoch."""
        if self.length < batch_size:
            raise DatasetError(
                f"{dataset_dir}: {len(self.slots)} committed trajectories"
                f"{'' if wanted is None else f' of the {len(wanted)} selected levels'} give reader {shard_index} of "
                f"{total_shard_count} only {self.length} per epoch, fewer than batch_size {batch_size}"
            )
        self.batches_per_epoch = self.length // batch_size
        self.epoch = 0
        """Epoch of the batch `load_next_batch` returned last."""
        self._render = None if render_fn is None else jax.jit(jax.vmap(jax.vmap(render_fn)))
        self._cache: dict[str, np.ndarray] | None = None
        if 0 < self.decoded_bytes(len(self.slots)) <= cache_bytes:
            self._cache = self._read_stored(self.slots)
        self._upcoming = itertools.islice(self._slot_batches(), start_batch, None)
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="loader") if prefetch else None
        self._queue: collections.deque[tuple[int, np.ndarray, Future]] = collections.deque()
        self._prefetch = prefetch

    @property
    def cached(self) -> bool:
        """The reader's trajectories are held in host memory."""
        return self._cache is not None

    def decoded_bytes(self, num_trajectories: int) -> int:
        """Host bytes of that many decoded trajectories as stored (per-level fields once, not over time)."""
        layout = self.dataset.layout
        per_trajectory = sum(
            np.dtype(spec.dtype).itemsize * int(np.prod(spec.full_shape(layout.num_steps)))
            for spec in layout.fields
            if spec.name in self._field_names()
        )
        return per_trajectory * num_trajectories

    def _field_names(self) -> list[str]:
        return [ACTION, ACTION_MASK, DONE, VALID] + [spec.name for spec in self.dataset.layout.state_fields]

    @staticmethod
    def _holds_wanted(record: BatchRecord, wanted: set[int] | None) -> bool:
        return any(_wanted(level, wanted) for level in record.levels)

    def _check_objects(self, records: list[BatchRecord]) -> None:
        """Fail closed: `DatasetError` naming the level batch and the array if a read field's object that a record
        commits is absent (a missing object would read as fill values: zeros, False) or, in a local folder, not of
        its recorded size (truncated). One listing of the data objects; checksums are `require_intact`'s."""
        store, root = self.dataset.store, self.dataset.root
        present = set(store.list(f"{DATA_DIR}/"))
        for record in records:
            where = f"{root}: {shard_name(record.shard)} batch {record.batch}"
            for name in self._field_names():
                entry = record.arrays.get(name)
                if entry is None:
                    raise DatasetError(f"{where}: array {name} is not in its commit record; run `kforge verify {root}`")
                if entry.file is None:
                    continue
                if entry.file not in present:
                    raise DatasetError(
                        f"{where}: array {name}: committed object {entry.file} is missing; run `kforge verify {root}`"
                    )
                if store.is_local and entry.size is not None and (size := store.size(entry.file)) != entry.size:
                    raise DatasetError(
                        f"{where}: array {name}: committed object {entry.file} is {size} bytes, its record says "
                        f"{entry.size} (truncated?); run `kforge verify {root}`"
                    )

    def _whole_objects(self, records: list[BatchRecord], max_bytes: int) -> dict[str, np.ndarray]:
        """Field -> bool per level batch: the per-step shard objects read whole (object stores only; sizes from the
        commit records, so none for records that do not size their objects)."""
        if self.dataset.store.is_local or max_bytes <= 0:
            return {}
        layout, num_batches = self.dataset.layout, self.dataset.geometry.num_batches
        whole = {spec.name: np.zeros(num_batches, bool) for spec in layout.fields if spec.per_step}
        for record in records:
            for name, entry in record.arrays.items():
                if name in whole and entry.size is not None and entry.size <= max_bytes:
                    whole[name][record.global_batch] = True
        return whole

    def _epoch_order(self, epoch: int) -> np.ndarray:
        permutation = np.random.default_rng([self.seed, epoch]).permutation(len(self.slots))
        return self.slots[
            permutation[: self.length * self.total_shard_count][self.shard_index :: self.total_shard_count]
        ]

    def _slot_batches(self) -> Iterator[tuple[int, np.ndarray]]:
        """(epoch, slots) of every batch of this reader, in order, endlessly."""
        epoch = 0
        while True:
            order = self._epoch_order(epoch)
            for start in range(0, self.batches_per_epoch * self.batch_size, self.batch_size):
                yield epoch, order[start : start + self.batch_size]
            epoch += 1

    def load_next_batch(self) -> ActionEnvStateMask:
        """The next batch of this reader; after `batches_per_epoch` batches a new epoch starts (new permutation)."""
        if self._pool is None:
            self.epoch, slots = next(self._upcoming)
            return self._to_batch(slots, self._read(slots))
        while len(self._queue) <= self._prefetch:
            epoch, slots = next(self._upcoming)
            self._queue.append((epoch, slots, self._pool.submit(self.load_slots, slots)))
        self.epoch, _, future = self._queue.popleft()
        return future.result()

    def close(self) -> None:
        """Stop prefetching; later batches are the same, read when asked for."""
        if self._pool is not None:
            for _, _, future in self._queue:
                future.cancel()
            self._pool.shutdown(wait=True)
            self._upcoming = itertools.chain([(epoch, slots) for epoch, slots, _ in self._queue], self._upcoming)
            self._pool, self._queue = None, collections.deque()

    def __enter__(self) -> TrajectoryDatasetManager:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def load_slots(self, slots: np.ndarray) -> ActionEnvStateMask:
        """The batch made of the given global slots (in that order); they must hold committed trajectories."""
        return self._to_batch(slots, self._read(slots))

    def _read_stored(self, slots: np.ndarray) -> dict[str, np.ndarray]:
        """Decoded arrays of the given slots as stored, checked to be committed."""
        slots = np.asarray(slots)
        try:
            arrays = self.dataset.read(self._field_names(), slots, self._whole)
        except DatasetError as error:  # a chunk that does not decode (crc32c): name the level batches read
            geometry = self.dataset.geometry
            batches = sorted({int(slot) // geometry.levels_per_batch for slot in slots})
            named = ", ".join(
                f"{shard_name(g // geometry.batches_per_shard)} batch {g % geometry.batches_per_shard}" for g in batches
            )
            raise DatasetError(f"{named}: {error}") from error
        empty = slots[~arrays[VALID]]
        if len(empty):
            raise DatasetError(
                f"{self.dataset.root}: committed slots {empty.tolist()} read as empty (missing data files?); "
                "run `kforge verify` on the dataset"
            )
        return arrays

    def _read(self, slots: np.ndarray) -> dict[str, np.ndarray]:
        """Host arrays of the given slots (decoded, static fields broadcast over time), checked to be kept."""
        slots = np.asarray(slots)
        rows = None if self._cache is None else np.searchsorted(self.slots, slots)
        if rows is not None and np.all(rows < len(self.slots)) and np.array_equal(self.slots[rows], slots):
            arrays = {name: value[rows] for name, value in self._cache.items()}
        else:
            arrays = self._read_stored(slots)
        layout = self.dataset.layout
        steps = layout.num_steps

        def over_time(name: str) -> np.ndarray:
            value = arrays[name]
            if layout.field(name).per_step:
                return value
            return np.broadcast_to(value[:, None], (value.shape[0], steps) + value.shape[1:])

        return {name: over_time(name) for name in self._field_names() if name != VALID}

    def _to_batch(self, slots: np.ndarray, arrays: dict[str, np.ndarray]) -> ActionEnvStateMask:
        layout = self.dataset.layout
        # One transfer of the whole batch rather than one per field.
        state, action, action_mask, done = jax.device_put(
            (
                {spec.name: arrays[spec.name] for spec in layout.state_fields},
                arrays[ACTION],
                arrays[ACTION_MASK],
                arrays[DONE],
            )
        )
        env_state = unflatten_state(layout, state)
        return ActionEnvStateMask(
            action=action,
            env_state=env_state,
            mask=jnp.ones(done.shape, bool),
            action_mask=action_mask,
            done=done,
            obs=None if self._render is None else self._render(env_state),
            trajectory_index=np.asarray(slots, np.int64),
        )
