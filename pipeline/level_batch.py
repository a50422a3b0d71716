"""The unit of work: one level batch of a shard, from level keys to expert windows, as a pure function.

A level's identity is its index in the split; every random choice about it derives from (split seed, index,
purpose), so its result does not depend on which worker ran it, when, or how often the job was resumed. The batch
shape is fixed by the config (XLA may round differently for another shape), and no computation mixes levels.
"""

from __future__ import annotations

import dataclasses
import enum

import jax
import jax.numpy as jnp
import numpy as np

from agents import Window, collect_windows, train_levels
from env import EnvParams, FilterReason, Level, StaticEnvParams, filter_levels, sample_levels
from pipeline.config import JobConfig, ppo_config


class KeyPurpose(enum.IntEnum):
    """What a per-level key is folded for: each purpose gets an independent stream."""

    SAMPLE = 0
    TRAIN = 1
    COLLECT = 2


class LevelStatus(enum.IntEnum):
    """Outcome of one level of the split."""

    KEPT = 0  # its expert's window was successful and is stored
    FILTERED = 1  # dropped by the trivial-level filter before training (see filter_reason)
    UNSOLVED = 2  # trained, but the expert's window was not successful
    FAILED = 3  # training or the rollout produced non-finite values (contained to this level)


def level_key(split_seed: int, level_index: int, purpose: KeyPurpose) -> jax.Array:
    """The PRNG key of one level for one purpose."""
    return jax.random.fold_in(jax.random.fold_in(jax.random.key(split_seed), level_index), purpose)


def level_keys(split_seed: int, level_indices: np.ndarray, purpose: KeyPurpose) -> jax.Array:
    return jax.vmap(lambda index: level_key(split_seed, index, purpose))(jnp.asarray(level_indices, jnp.uint32))


def batch_level_indices(job: JobConfig, shard: int, batch: int) -> np.ndarray:
    """Split-level indices of a level batch; the last shard may run past num_levels (those slots are padding)."""
    start = shard * job.work.levels_per_shard + batch * job.work.levels_per_batch
    return np.arange(start, start + job.work.levels_per_batch)


def num_shards(job: JobConfig) -> int:
    return -(-job.split.num_levels // job.work.levels_per_shard)


def batches_per_shard(job: JobConfig) -> int:
    return job.work.levels_per_shard // job.work.levels_per_batch


@dataclasses.dataclass(frozen=True)
class LevelBatchResult:
    """Host-side results of a level batch (leading axis = levels of the batch)."""

    level_indices: np.ndarray  # (B,) i64 index of each level in the split
    in_split: np.ndarray  # (B,) bool: False for padding past split.num_levels
    status: np.ndarray  # (B,) i32 `LevelStatus`
    filter_reason: np.ndarray  # (B,) i32 `env.FilterReason` (KEPT when not filtered)
    final_success_rate: np.ndarray  # (B,) f32 success rate of the expert's last training update (NaN if none)
    learning_curve: np.ndarray  # (B, U) f32 success rate per training update
    window: Window  # host arrays (B, W, ...): the expert windows, stored for KEPT levels


def environment(job: JobConfig) -> tuple[EnvParams, StaticEnvParams]:
    return EnvParams(dense_reward_scale=job.env.dense_reward_scale), StaticEnvParams.for_size(job.split.size)


def sample_batch(job: JobConfig, level_indices: np.ndarray) -> Level:
    """The batch's levels, regenerated from their indices."""
    _, static = environment(job)
    return sample_levels(level_keys(job.split.seed, level_indices, KeyPurpose.SAMPLE), static)


def run_level_batch(job: JobConfig, shard: int, batch: int) -> LevelBatchResult:
    """Sample, filter, train and roll out one level batch; a pure function of (config, shard, batch)."""
    params, static = environment(job)
    indices = batch_level_indices(job, shard, batch)
    in_split = indices < job.split.num_levels
    levels = sample_batch(job, indices)

    filtered = jax.device_get(filter_levels(levels, params, static, noop_steps=job.filter.noop_steps))
    dropped = ~filtered.keep if job.filter.enabled else np.zeros_like(filtered.keep)
    reason = np.where(dropped, filtered.reason, FilterReason.KEPT)

    config = ppo_config(job)
    trained = train_levels(levels, level_keys(job.split.seed, indices, KeyPurpose.TRAIN), config, params, static)
    window = collect_windows(
        trained.params,
        levels,
        level_keys(job.split.seed, indices, KeyPurpose.COLLECT),
        config,
        params,
        static,
        num_steps=job.collect.window_steps,
        greedy=job.collect.greedy,
    )
    window, metrics = jax.device_get((window, trained.metrics))
    finite = _finite_per_level(trained.params) & _finite_per_level(window)
    status = np.where(
        dropped,
        LevelStatus.FILTERED,
        np.where(~finite, LevelStatus.FAILED, np.where(window.successful, LevelStatus.KEPT, LevelStatus.UNSOLVED)),
    )
    curve = np.asarray(metrics.success_rate, np.float32)
    return LevelBatchResult(
        level_indices=indices,
        in_split=in_split,
        status=status.astype(np.int32),
        filter_reason=reason.astype(np.int32),
        final_success_rate=curve[:, -1],
        learning_curve=curve,
        window=window,
    )


def _finite_per_level(tree) -> np.ndarray:
    """(B,) bool: every floating leaf of the level's slice is finite."""
    checks = [
        np.all(np.isfinite(np.asarray(x)).reshape(x.shape[0], -1), axis=1)
        for x in jax.tree.leaves(jax.device_get(tree))
        if np.issubdtype(np.asarray(x).dtype, np.floating)
    ]
    return np.logical_and.reduce(checks)
