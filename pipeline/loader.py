"""Batches of stored trajectories for users, with the interface of Kinetix's `TrajectoryDatasetManager`.

Only committed, kept trajectories are read. Order: each epoch is a permutation of all trajectories drawn from
(seed, epoch); data-parallel reader r of R takes every R-th entry of it starting at r (so readers are disjoint and
together cover the epoch, up to the remainder that R does not divide); its batches are consecutive runs of its part,
and the last incomplete batch of an epoch is dropped (it differs from epoch to epoch).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from env import EnvState, StaticEnvParams
from pipeline.layout import ACTION, ACTION_MASK, DONE, VALID, DatasetError, unflatten_state
from pipeline.manifest import iter_records
from pipeline.shard_store import open_dataset


class ActionEnvStateMask(NamedTuple):
    """One batch (Kinetix's `ActionEnvStateMask` plus the rendered observation and the trajectories' slots)."""

    action: jnp.ndarray  # (B, T, *action shape)
    env_state: EnvState  # leaves (B, T, ...); per-level leaves broadcast over time
    mask: jnp.ndarray  # (B, T) bool, all True (every stored step is real)
    action_mask: jnp.ndarray  # (B, T, 6) bool, the level's mask broadcast over time
    done: jnp.ndarray  # (B, T) bool
    obs: Any  # render_fn(env_state) with leading (B, T), or None without a render_fn
    trajectory_index: np.ndarray  # (B,) global slot of each trajectory in the dataset


class TrajectoryDatasetManager:
    """Endless deterministic batches of (B, T, ...) trajectories from a dataset directory.

    `render_fn(env_state) -> observation` of one state (e.g. `lambda s: env.observe(s, static, type)`) is applied
    to every step of a batch, compiled once.
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
    ):
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        if not 0 <= shard_index < total_shard_count:
            raise ValueError(f"shard_index {shard_index} out of range [0, {total_shard_count})")
        self.dataset = open_dataset(dataset_dir)
        if static_env_params is not None and static_env_params != self.dataset.layout.static:
            raise DatasetError(
                f"{dataset_dir}: stored with {self.dataset.layout.static}, but {static_env_params} was requested"
            )
        self.batch_size, self.seed = batch_size, seed
        self.shard_index, self.total_shard_count = shard_index, total_shard_count
        self.slots = np.array(
            sorted(
                level["slot"] for record in iter_records(dataset_dir) for level in record["levels"] if level["kept"]
            ),
            np.int64,
        )
        self.length = len(self.slots) // total_shard_count
        """Trajectories this reader sees per epoch."""
        if self.length < batch_size:
            raise DatasetError(
                f"{dataset_dir}: {len(self.slots)} committed trajectories give reader {shard_index} of "
                f"{total_shard_count} only {self.length} per epoch, fewer than batch_size {batch_size}"
            )
        self.batches_per_epoch = self.length // batch_size
        self.epoch, self._batch = 0, 0
        self._order = self._epoch_order(0)
        self._render = None if render_fn is None else jax.jit(jax.vmap(jax.vmap(render_fn)))

    def _epoch_order(self, epoch: int) -> np.ndarray:
        permutation = np.random.default_rng([self.seed, epoch]).permutation(len(self.slots))
        return self.slots[
            permutation[: self.length * self.total_shard_count][self.shard_index :: self.total_shard_count]
        ]

    def load_next_batch(self) -> ActionEnvStateMask:
        """The next batch of this reader; after `batches_per_epoch` batches a new epoch starts (new permutation)."""
        if self._batch == self.batches_per_epoch:
            self.epoch, self._batch = self.epoch + 1, 0
            self._order = self._epoch_order(self.epoch)
        start = self._batch * self.batch_size
        self._batch += 1
        return self.load_slots(self._order[start : start + self.batch_size])

    def load_slots(self, slots: np.ndarray) -> ActionEnvStateMask:
        """The batch made of the given global slots (in that order); they must hold committed trajectories."""
        layout = self.dataset.layout
        names = [ACTION, ACTION_MASK, DONE, VALID] + [spec.name for spec in layout.state_fields]
        arrays = self.dataset.read(names, np.asarray(slots))
        empty = np.asarray(slots)[~arrays[VALID]]
        if len(empty):
            raise DatasetError(
                f"{self.dataset.root}: committed slots {empty.tolist()} read as empty (missing data files?); "
                "run `kforge verify` on the dataset"
            )
        steps = layout.num_steps

        def over_time(name: str) -> np.ndarray:
            value = arrays[name]
            if layout.field(name).per_step:
                return value
            return np.broadcast_to(value[:, None], (value.shape[0], steps) + value.shape[1:])

        # One transfer of the whole batch rather than one per field.
        state, action, action_mask, done = jax.device_put(
            (
                {spec.name: over_time(spec.name) for spec in layout.state_fields},
                arrays[ACTION],
                over_time(ACTION_MASK),
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
