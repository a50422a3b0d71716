"""The unit of work: one level batch of a shard, from level keys to expert windows, as a pure function.

A level's identity is its index in the split; every random choice about it derives from (split seed, index,
purpose), so its result does not depend on which worker ran it, when, or how often the job was resumed. The batch
shape is fixed by the config (XLA may round differently for another shape), and no computation mixes levels. A
worker with several local devices (GPUs, or `XLA_FLAGS=--xla_force_host_platform_device_count`) trains and rolls out
the batch spread over them when their count divides it (`pipeline.generation.devices`).
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import queue
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from kforge.agents import WindowPlan, collect_windows, initial_params, train_levels
from kforge.env import FilterReason, Level, filter_levels, sample_levels
from kforge.pipeline.generation.devices import over_local_devices
from kforge.pipeline.generation.estimated_progress import ProgressListener, estimated_progress
from kforge.pipeline.generation.resolved import ResolvedJob
from kforge.pipeline.generation.schema import FIXED_BUDGET_MODE, JobConfig
from kforge.pipeline.storage import BatchTrajectories, Outcome, learning_curves


class KeyPurpose(enum.IntEnum):
    """What a per-level key is folded for: each purpose gets an independent stream."""

    SAMPLE = 0
    TRAIN = 1
    COLLECT = 2


def level_key(split_seed: int, level_index: int, purpose: KeyPurpose) -> jax.Array:
    """The PRNG key of one level for one purpose."""
    return jax.random.fold_in(jax.random.fold_in(jax.random.key(split_seed), level_index), purpose)


def level_keys(split_seed: int, level_indices: np.ndarray, purpose: KeyPurpose) -> jax.Array:
    return jax.vmap(lambda index: level_key(split_seed, index, purpose))(jnp.asarray(level_indices, jnp.uint32))


def batch_level_indices(job: JobConfig | ResolvedJob, shard: int, batch: int) -> np.ndarray:
    """Split-level indices of a level batch; the last shard may run past num_levels (those slots are padding)."""
    start = shard * job.work.levels_per_shard + batch * job.work.levels_per_batch
    return np.arange(start, start + job.work.levels_per_batch)


def num_shards(job: JobConfig | ResolvedJob) -> int:
    return -(-job.split.num_levels // job.work.levels_per_shard)


def batches_per_shard(job: JobConfig | ResolvedJob) -> int:
    return job.work.levels_per_shard // job.work.levels_per_batch


def sample_batch(job: ResolvedJob, level_indices: np.ndarray) -> Level:
    """The batch's levels, regenerated from their indices."""
    keys = level_keys(job.split.seed, level_indices, KeyPurpose.SAMPLE)
    return _compiling_sample_program(job, keys).result()(keys)


def _batch_shapes(job: ResolvedJob, level_indices: np.ndarray) -> Level:
    """The shapes and types of `sample_batch`'s levels (nothing compiled or run)."""
    static = job.static
    keys = level_keys(job.split.seed, level_indices, KeyPurpose.SAMPLE)
    return jax.eval_shape(functools.partial(sample_levels, static=static), keys)


def _compiling_sample_program(job: ResolvedJob, keys: jax.Array) -> Future:
    """The future of `env.sample_levels` for the job's batches of this many levels: traced here and compiled in the
    background, once per process (so a level batch's first step compiles beside the training program)."""
    static = job.static
    program = (static, keys.shape[0])
    compiling = _sample_programs.get(program)
    if compiling is None or (compiling.done() and compiling.exception() is not None):
        lowered = sample_levels.lower(keys, static)
        compiling = _sample_programs[program] = _in_background(lowered.compile)
    return compiling


_sample_programs: dict[tuple, Future] = {}


@dataclasses.dataclass(frozen=True)
class SampledBatch:
    """A level batch as sampled and filtered, before its experts train (leading axis L)."""

    indices: np.ndarray  # (L,) int split-level index of each level
    levels: Level
    filtered: object  # the filter's verdicts (`env.filter_levels`), leaves (L,)
    dropped: np.ndarray  # (L,) bool: dropped by the filter


def sample_and_filter(job: ResolvedJob, indices: np.ndarray) -> SampledBatch:
    """The level batch of split-level `indices`, sampled and filtered."""
    levels = sample_batch(job, indices)
    return SampledBatch(indices, levels, *filter_batch(job, levels))


def filter_batch(job: ResolvedJob, levels: Level):
    """(the filter's verdicts, (L,) bool dropped by the filter) of a level batch's levels."""
    filtered = jax.device_get(_compiling_filter_program(job, levels).result()(levels, job.env_params))
    dropped = ~filtered.keep if job.filter.enabled else np.zeros_like(filtered.keep)
    return filtered, dropped


def _compiling_filter_program(job: ResolvedJob, levels: Level) -> Future:
    """The future of `env.filter_levels` as one program for the job's level batches of this size: traced here
    (`levels` may be abstract) and compiled in the background, once per process."""
    env_params, static = job.env_params, job.static
    program = (static, job.filter.noop_steps, jax.tree.structure(levels), jax.tree.leaves(levels)[0].shape[0])
    compiling = _filter_programs.get(program)
    if compiling is None or (compiling.done() and compiling.exception() is not None):
        verdicts = functools.partial(filter_levels, static=static, noop_steps=job.filter.noop_steps)
        lowered = jax.jit(verdicts).lower(levels, env_params)
        compiling = _filter_programs[program] = _in_background(lowered.compile)
    return compiling


_filter_programs: dict[tuple, Future] = {}


def run_level_batch(
    job: ResolvedJob, shard: int, batch: int, on_progress: ProgressListener | None = None
) -> BatchTrajectories:
    """Sample, filter, train and roll out one level batch; a pure function of (config, shard, batch).

    Every level gets an outcome (`level_outcome`); only kept levels' windows are stored. Levels past
    `split.num_levels` (padding of the last shard) are computed with the rest but never kept. `on_progress` is told
    the PPO updates done per level once the training program is compiled, an estimate of them while the experts
    train (from another thread; `estimated_progress`), and all of them once trained.
    """
    clock = PhaseClock()
    params = job.env_params
    indices = batch_level_indices(job, shard, batch)
    config = job.ppo
    train_keys = level_keys(job.split.seed, indices, KeyPurpose.TRAIN)
    _compiling_sample_program(job, level_keys(job.split.seed, indices, KeyPurpose.SAMPLE))
    compiling_train = _compiling_train_program(job, indices, train_keys)
    abstract_levels = _batch_shapes(job, indices)
    _compiling_filter_program(job, abstract_levels)
    _compiling_collect_program(job, abstract_levels, level_keys(job.split.seed, indices, KeyPurpose.COLLECT))
    sampled = sample_and_filter(job, indices)
    clock.lap("sample_and_filter")

    train = compiling_train.result()
    with estimated_progress(train, config.num_updates, on_progress or _ignore_progress):
        trained = jax.block_until_ready(train(sampled.levels, train_keys, params))
    clock.lap("train")
    metrics, selection = jax.device_get((trained.metrics, trained.selection))
    experts = Experts(
        params=trained.params,
        success_rate=selection.at_best(selection.success_rate).astype(np.float32),
        env_steps=selection.at_best(selection.env_steps).astype(np.int64),
        trained_env_steps=np.full(indices.shape, config.env_steps_per_level, np.int64),
        curve_success_rate=np.asarray(metrics.success_rate),
        curve_mean_return=np.asarray(metrics.mean_return),
    )
    return batch_result(job, sampled, experts, clock, FIXED_BUDGET_MODE)


class Experts(NamedTuple):
    """The trained experts of a level batch (leading axis L), as the dataset records them."""

    params: dict  # network parameters of each level's expert
    success_rate: np.ndarray  # (L,) f32 [-] evaluation success rate of the expert
    env_steps: np.ndarray  # (L,) int [env steps] the expert had trained for
    trained_env_steps: np.ndarray  # (L,) int [env steps] the level's training used
    curve_success_rate: np.ndarray  # (L, U) f32 per update (NaN: no episode ended or the update did not run)
    curve_mean_return: np.ndarray  # (L, U) f32


def batch_result(
    job: ResolvedJob, sampled: SampledBatch, experts: Experts, clock: PhaseClock, budget_mode: str
) -> BatchTrajectories:
    """Roll out every expert of the batch for its window, and each level's outcome: the batch's data."""
    config, indices, filtered, dropped = job.ppo, sampled.indices, sampled.filtered, sampled.dropped
    window = jax.device_get(_windows(job, experts.params, sampled.levels, indices))
    clock.lap("collect")
    finite = _finite_per_level(experts.params) & _finite_per_level(window)
    in_split = indices < job.split.num_levels
    outcomes = [
        level_outcome(bool(in_split[i]), bool(dropped[i]), int(filtered.reason[i]), bool(finite[i]), bool(ok))
        for i, ok in enumerate(window.successful)
    ]
    return BatchTrajectories(
        states=window.states,
        action=window.actions,
        done=window.done,
        success=window.success,
        kept=np.array([outcome == Outcome.KEPT for outcome in outcomes]),
        level_id=indices,
        level_seed=np.full(indices.shape, job.split.seed),
        expert_success_rate=experts.success_rate,
        expert_env_steps=experts.env_steps,
        trained_env_steps=experts.trained_env_steps,
        budget_mode=budget_mode,
        outcome=outcomes,
        curves=learning_curves(experts.curve_success_rate, experts.curve_mean_return, config.steps_per_update),
        seconds=clock.seconds,
    )


def _compiling_train_program(job: ResolvedJob, indices: np.ndarray, keys: jax.Array) -> Future:
    """The future of `train_levels` for the job's level batches of this size, spread over the local devices:
    compiled (or loaded from the persistent compilation cache) once per config and level count in a process.
    It is traced here, before the batch is sampled (tracing is Python: it holds the GIL), and compiled in the
    background while the calling thread traces the filter and collection programs and samples and filters the batch
    (XLA compiles without holding the GIL)."""
    env_params, static = job.env_params, job.static
    config = job.ppo
    program = (config, static, len(keys))
    compiling = _train_programs.get(program)
    if compiling is None or (compiling.done() and compiling.exception() is not None):

        def train(levels, keys, env_params):
            return train_levels(levels, keys, config, env_params, static)

        levels = _batch_shapes(job, indices)
        spread = over_local_devices(train, len(keys), level_args=2, shared_args=1)
        lowered = jax.jit(spread).lower(levels, keys, env_params)
        compiling = _train_programs[program] = _in_background(lowered.compile)
    return compiling


_train_programs: dict[tuple, Future] = {}


COMPILE_THREADS = 2
"""Compilations in flight at once (`_in_background`): two keep two cores busy; each holds its program's HLO and
machine code in memory (a quickstart process with six at once held 4 GB when a shared machine ran out of memory)."""


def _in_background(function: Callable[[], object]) -> Future:
    """The future of `function()` (a compilation), run by one of `COMPILE_THREADS` daemon threads in the
    order asked for (an interrupted job exits without waiting for them)."""
    future = Future()
    _compile_queue.put((function, future))
    with _compile_threads_lock:
        while len(_compile_threads) < COMPILE_THREADS:
            thread = threading.Thread(target=_compile_forever, name=f"compile-{len(_compile_threads)}", daemon=True)
            _compile_threads.append(thread)
            thread.start()
    return future


def _compile_forever() -> None:
    while True:
        function, future = _compile_queue.get()
        try:
            future.set_result(function())
        except BaseException as error:  # handed to whoever waits for the result
            future.set_exception(error)


_compile_queue: queue.SimpleQueue = queue.SimpleQueue()
_compile_threads: list[threading.Thread] = []
_compile_threads_lock = threading.Lock()


def _compiled_collect_program(job: ResolvedJob, levels: Level, keys: jax.Array) -> jax.stages.Compiled:
    """`_collect_program` for this job and level count, compiled (or loaded from the persistent compilation cache)
    once per process (`_compiling_collect_program`)."""
    return _compiling_collect_program(job, levels, keys).result()


def _compiling_collect_program(job: ResolvedJob, levels: Level, keys: jax.Array) -> Future:
    """The future of `_compiled_collect_program`: traced here (`levels` may be abstract: the experts' parameters have
    the shapes of fresh ones, so nothing needs to be trained first) and compiled in the background, so that it
    compiles beside the training program and while the experts train."""
    env_params, static = job.env_params, job.static
    config = job.ppo
    program = (WindowPlan(config, static, job.collect.window_steps, job.collect.greedy), len(keys))
    compiling = _collect_programs.get(program)
    if compiling is None or (compiling.done() and compiling.exception() is not None):
        params = jax.eval_shape(jax.vmap(lambda key: initial_params(key, config, static)), keys)
        lowered = jax.jit(_collect_program(*program)).lower(params, levels, keys, env_params)
        compiling = _collect_programs[program] = _in_background(lowered.compile)
    return compiling


_collect_programs: dict[tuple, Future] = {}


def windows_successful(job: ResolvedJob, params, levels: Level, indices: np.ndarray) -> np.ndarray:
    """(L,) bool: whether each level's window, rolled out with `params` as `batch_result` rolls out a level batch
    of L levels (the same program and keys), would count as successful."""
    return np.asarray(jax.device_get(_windows(job, params, levels, indices).successful))


def _windows(job: ResolvedJob, params, levels: Level, indices: np.ndarray):
    env_params = job.env_params
    keys = level_keys(job.split.seed, indices, KeyPurpose.COLLECT)
    return _compiled_collect_program(job, levels, keys)(params, levels, keys, env_params)


def _collect_program(plan: WindowPlan, num_levels: int):
    """(expert params, levels, keys, env params) -> `collect_windows`, spread over the local devices."""

    def collect(params, levels, keys, env_params):
        return collect_windows(params, levels, keys, plan, env_params)

    return over_local_devices(collect, num_levels, level_args=3, shared_args=1)


def _ignore_progress(updates_done: int, num_updates: int) -> None:
    pass


class PhaseClock:
    """Wall time of consecutive phases, in seconds by phase name."""

    def __init__(self):
        self.seconds: dict[str, float] = {}
        self._last = time.perf_counter()

    def restart(self) -> None:
        """Start the next phase now: the time since the last lap belongs to no phase."""
        self._last = time.perf_counter()

    def lap(self, phase: str) -> None:
        now = time.perf_counter()
        self.seconds[phase] = now - self._last
        self._last = now


def level_outcome(in_split: bool, dropped: bool, reason: int, finite: bool, successful: bool) -> Outcome:
    """Why a level was or was not kept: kept, padding, filtered:<reason>, failed or unsolved."""
    if not in_split:
        return Outcome.PADDING
    if dropped:
        return Outcome.filtered(FilterReason(reason).name.lower())
    if not finite:
        return Outcome.FAILED
    return Outcome.KEPT if successful else Outcome.UNSOLVED


def _finite_per_level(tree) -> np.ndarray:
    """(B,) bool: every floating leaf of the level's slice is finite."""
    checks = [
        np.all(np.isfinite(np.asarray(x)).reshape(x.shape[0], -1), axis=1)
        for x in jax.tree.leaves(jax.device_get(tree))
        if np.issubdtype(np.asarray(x).dtype, np.floating)
    ]
    return np.logical_and.reduce(checks)
