"""Streamed and adaptive budgets (`experts.budget_mode: streamed | adaptive`): a shard's levels stream through the
slots of one training program; streamed, each level trains the whole budget; adaptive, only until its evaluations
decide.

The program trains `work.levels_per_batch` slots together for one evaluation period at a time
(`agents.train_segments`). After each period a level stops when its budget is spent or, adaptive only, when its
last `experts.solved_evaluations` evaluations all succeeded in every episode and the window its expert would store
succeeds (solved: a level stopped as solved is kept), or it has trained
`experts.give_up_env_steps` without one successful episode in training or evaluation (given up); its slot then takes
the next level of the shard, claiming the shard's next level batch when needed, so the program stays full. Levels the
filter drops take no slot. A level batch is rolled out and handed back once all its levels are done. A level's
training depends only on its key (level index and split seed) and the config, not on its slot, the levels beside it
or when it ran.
"""

from __future__ import annotations

import collections
import dataclasses
import enum
import math
import time
from collections.abc import Callable, Iterator

import jax
import jax.numpy as jnp
import numpy as np

from kforge.agents import PPOConfig, check_segmented, put_slot, start_level, train_segments
from kforge.pipeline.generation.level_batch import (
    Experts,
    KeyPurpose,
    PhaseClock,
    SampledBatch,
    batch_level_indices,
    batch_result,
    level_key,
    sample_and_filter,
    windows_successful,
)
from kforge.pipeline.generation.resolved import ResolvedJob
from kforge.pipeline.generation.schema import ADAPTIVE_BUDGET_MODE
from kforge.pipeline.storage import BatchTrajectories


class Verdict(enum.Enum):
    """Why a level's training stopped."""

    SOLVED = "solved"  # its last evaluations succeeded in every episode, and so does its window
    GAVE_UP = "gave_up"  # no successful episode by the give-up point
    BUDGET_SPENT = "budget_spent"  # trained the whole budget


@dataclasses.dataclass(frozen=True)
class StopRule:
    """When a level stops training, in evaluations (one per segment of `select_every_updates` updates)."""

    solved_evaluations: int  # consecutive evaluations with every episode successful
    solved_window: bool  # and only once the window the expert would store succeeds
    give_up_evaluations: int  # evaluations without any successful episode after which the level gives up
    num_evaluations: int  # evaluations of the whole budget

    @classmethod
    def of(cls, job: ResolvedJob) -> StopRule:
        """The job's rule: adaptive's, or for the streamed mode one that only stops when the budget is spent."""
        config = job.ppo
        segment_steps = config.select_every_updates * config.steps_per_update
        num_evaluations = config.num_updates // config.select_every_updates
        if job.experts.budget_mode != ADAPTIVE_BUDGET_MODE:
            never = num_evaluations + 1
            return cls(
                solved_evaluations=never, solved_window=True, give_up_evaluations=never, num_evaluations=num_evaluations
            )
        return cls(
            solved_evaluations=job.experts.solved_evaluations,
            solved_window=job.experts.solved_window,
            give_up_evaluations=math.ceil(job.experts.give_up_env_steps / segment_steps),
            num_evaluations=num_evaluations,
        )

    def evaluations_solved(self, success_rates: list[float]) -> bool:
        """Whether the last `solved_evaluations` evaluations succeeded in every episode."""
        recent = success_rates[-self.solved_evaluations :]
        return len(success_rates) >= self.solved_evaluations and all(rate >= 1.0 for rate in recent)

    def verdict(
        self, success_rates: list[float], succeeded_in_training: bool, window_successful: bool = False
    ) -> Verdict | None:
        """The verdict after the evaluations so far (`success_rates`), given whether the window the level's expert
        would store is successful (unless `solved_window` is off), or None to train on."""
        done = len(success_rates)
        if (window_successful or not self.solved_window) and self.evaluations_solved(success_rates):
            return Verdict.SOLVED
        if done >= self.num_evaluations:
            return Verdict.BUDGET_SPENT
        if done >= self.give_up_evaluations and not succeeded_in_training and max(success_rates) <= 0.0:
            return Verdict.GAVE_UP
        return None


@dataclasses.dataclass
class _LevelRun:
    """A level in a slot: where it belongs and what its evaluations said so far."""

    batch: int
    position: int  # in its level batch
    success_rates: list[float] = dataclasses.field(default_factory=list)
    succeeded_in_training: bool = False
    curve_success_rate: list[np.ndarray] = dataclasses.field(default_factory=list)
    curve_mean_return: list[np.ndarray] = dataclasses.field(default_factory=list)


@dataclasses.dataclass
class _BatchWork:
    """A claimed level batch while its levels train."""

    batch: int
    sampled: SampledBatch
    clock: PhaseClock
    num_updates: dataclasses.InitVar[int]  # PPO updates of the whole budget (the learning curves' length)
    params: list = dataclasses.field(init=False)  # per position: the expert's parameters (None until done)
    success_rate: np.ndarray = dataclasses.field(init=False)  # (L,) f32, NaN until done
    env_steps: np.ndarray = dataclasses.field(init=False)  # (L,) int
    trained_env_steps: np.ndarray = dataclasses.field(init=False)  # (L,) int
    curve_success_rate: np.ndarray = dataclasses.field(init=False)  # (L, U) f32, NaN where not trained
    curve_mean_return: np.ndarray = dataclasses.field(init=False)  # (L, U) f32
    train_seconds: float = 0.0

    def __post_init__(self, num_updates: int):
        count, curve = len(self.sampled.indices), (len(self.sampled.indices), num_updates)
        self.params = [None] * count
        self.success_rate = np.full(count, np.nan, np.float32)
        self.env_steps, self.trained_env_steps = np.zeros(count, np.int64), np.zeros(count, np.int64)
        self.curve_success_rate = np.full(curve, np.nan, np.float32)
        self.curve_mean_return = np.full(curve, np.nan, np.float32)

    @property
    def pending(self) -> int:
        return sum(params is None for params in self.params)


def streamed_level_batches(
    job: ResolvedJob,
    shard: int,
    claim: Callable[[], int | None],
    on_progress: Callable[[int, int, int], None] | None = None,
) -> Iterator[tuple[int, BatchTrajectories]]:
    """(batch, its data) for every level batch of `shard` that `claim` hands out (None: no more), each as soon as
    all its levels are trained and rolled out. `on_progress(batch, updates done, updates of the whole budget)` is
    told after every evaluation period, summed over the batch's levels."""
    check_segmented(job.ppo)
    yield from _SlotStream(job, shard, claim).batches(on_progress)


class _SlotStream:
    """The slots of one training program over a shard's levels: claimed level batches queue their trainable levels,
    each free slot takes the next, and a batch is handed back once its last level stops."""

    def __init__(self, job: ResolvedJob, shard: int, claim: Callable[[], int | None]):
        self.job, self.shard, self.claim = job, shard, claim
        self.rule = StopRule.of(job)
        self.num_slots = job.work.levels_per_batch
        self.segment_steps = job.ppo.select_every_updates * job.ppo.steps_per_update
        self.works: dict[int, _BatchWork] = {}
        self.queue: collections.deque[_LevelRun] = collections.deque()
        self.slots: list[_LevelRun | None] = [None] * self.num_slots
        self.slot_levels = self.trainings = None  # stacked over the slots once the first level starts
        self.claiming = True

    def batches(self, on_progress) -> Iterator[tuple[int, BatchTrajectories]]:
        """Fill the free slots, train one evaluation period, stop the levels whose verdict is in; until no level is
        left. Yields each batch as soon as it is complete."""
        while True:
            yield from self._fill_slots()
            occupied = [slot for slot in range(self.num_slots) if self.slots[slot] is not None]
            if not occupied:
                return
            self._train_period(occupied)
            ready = self._stop_decided(occupied, self._windows_successful(occupied))
            if on_progress is not None:
                _report(on_progress, self.works, self.slots, self.job.ppo)
            yield from ready

    def _fill_slots(self) -> list[tuple[int, BatchTrajectories]]:
        """Start a queued level in every free slot, claiming batches while the queue is empty; returns the claimed
        batches that had nothing to train."""
        ready = []
        for slot in range(self.num_slots):
            if self.slots[slot] is not None:
                continue
            while not self.queue and self.claiming:
                ready += self._claim_work()
            if not self.queue:
                break
            self._start(slot, self.queue.popleft())
        return ready

    def _start(self, slot: int, run: _LevelRun) -> None:
        """Put the level of `run`, freshly initialised, in `slot`."""
        work = self.works[run.batch]
        level = _level_at(work.sampled.levels, run.position)
        training = start_level(level, self._train_key(work, run.position), self.job.ppo, self.job.static)
        if self.trainings is None:  # the first level fills every slot; the others take theirs as they come
            self.slot_levels = jax.tree.map(lambda x: jnp.stack([x] * self.num_slots), level)
            self.trainings = jax.tree.map(lambda x: jnp.stack([x] * self.num_slots), training)
        else:
            self.slot_levels = put_slot(self.slot_levels, jnp.int32(slot), level)
            self.trainings = put_slot(self.trainings, jnp.int32(slot), training)
        self.slots[slot] = run

    def _train_key(self, work: _BatchWork, position: int) -> jax.Array:
        return level_key(self.job.split.seed, int(work.sampled.indices[position]), KeyPurpose.TRAIN)

    def _claim_work(self) -> list[tuple[int, BatchTrajectories]]:
        """Claim and prepare the next level batch: its trainable levels join the queue; the rest get fresh
        parameters (they are never kept). Returns it at once if it has nothing to train."""
        batch = self.claim()
        if batch is None:
            self.claiming = False
            return []
        job, clock = self.job, PhaseClock()
        indices = batch_level_indices(job, self.shard, batch)
        sampled = sample_and_filter(job, indices)
        work = _BatchWork(batch, sampled, clock, job.ppo.num_updates)
        clock.lap("sample_and_filter")
        self.works[batch] = work
        for position in range(len(indices)):
            if sampled.dropped[position] or indices[position] >= job.split.num_levels:
                key = self._train_key(work, position)
                fresh = start_level(_level_at(sampled.levels, position), key, job.ppo, job.static)
                work.params[position] = jax.device_get(fresh.best.params)
            else:
                self.queue.append(_LevelRun(batch, position))
        return [self._finish(work)] if work.pending == 0 else []

    def _train_period(self, occupied: list[int]) -> None:
        """Train every slot one evaluation period and record the evaluation of each occupied one."""
        started = time.perf_counter()
        job = self.job
        self.trainings, output = train_segments(self.slot_levels, self.trainings, job.ppo, job.env_params, job.static)
        output = jax.device_get(output)
        seconds = time.perf_counter() - started
        for slot in occupied:
            run = self.slots[slot]
            self.works[run.batch].train_seconds += seconds / len(occupied)
            run.success_rates.append(float(output.success_rate[slot]))
            rates = np.asarray(output.metrics.success_rate[slot])
            run.succeeded_in_training |= bool(np.nanmax(rates, initial=0.0) > 0.0)
            run.curve_success_rate.append(rates)
            run.curve_mean_return.append(np.asarray(output.metrics.mean_return[slot]))

    def _windows_successful(self, occupied: list[int]) -> np.ndarray:
        """(slots,) bool: whether each slot's window would succeed; rolled out only when the rule needs it and a
        level's evaluations say solved."""
        rule, slots = self.rule, self.slots
        if not (rule.solved_window and any(rule.evaluations_solved(slots[slot].success_rates) for slot in occupied)):
            return np.zeros(self.num_slots, bool)
        started = time.perf_counter()
        indices = [self.works[run.batch].sampled.indices[run.position] if run is not None else 0 for run in slots]
        params = self.trainings.best.params
        successful = windows_successful(self.job, params, self.slot_levels, np.asarray(indices))
        for slot in occupied:
            self.works[slots[slot].batch].train_seconds += (time.perf_counter() - started) / len(occupied)
        return successful

    def _stop_decided(self, occupied: list[int], window_successful: np.ndarray) -> list[tuple[int, BatchTrajectories]]:
        """Free the slots whose level has a verdict; returns the batches those levels completed."""
        ready = []
        for slot in occupied:
            run = self.slots[slot]
            verdict = self.rule.verdict(run.success_rates, run.succeeded_in_training, bool(window_successful[slot]))
            if verdict is not None:
                self.slots[slot] = None
                ready += self._done(slot, run)
        return ready

    def _done(self, slot: int, run: _LevelRun) -> list[tuple[int, BatchTrajectories]]:
        """Record the level of `slot`, which has stopped, in its batch; the batch if it is complete."""
        work = self.works[run.batch]
        best = jax.device_get(jax.tree.map(lambda x: x[slot], self.trainings.best))
        trained = len(run.success_rates)
        work.params[run.position] = best.params
        work.success_rate[run.position] = run.success_rates[int(best.index)]
        work.env_steps[run.position] = (int(best.index) + 1) * self.segment_steps
        work.trained_env_steps[run.position] = trained * self.segment_steps
        updates = trained * self.job.ppo.select_every_updates
        work.curve_success_rate[run.position, :updates] = np.concatenate(run.curve_success_rate)
        work.curve_mean_return[run.position, :updates] = np.concatenate(run.curve_mean_return)
        return [self._finish(work)] if work.pending == 0 else []

    def _finish(self, work: _BatchWork) -> tuple[int, BatchTrajectories]:
        """Roll out the complete batch `work`: its data."""
        del self.works[work.batch]
        work.clock.seconds["train"] = work.train_seconds  # its share of the segments its levels trained in
        work.clock.restart()
        experts = Experts(
            params=jax.tree.map(lambda *leaves: jnp.stack(leaves), *work.params),
            success_rate=work.success_rate,
            env_steps=work.env_steps,
            trained_env_steps=work.trained_env_steps,
            curve_success_rate=work.curve_success_rate,
            curve_mean_return=work.curve_mean_return,
        )
        return work.batch, batch_result(self.job, work.sampled, experts, work.clock, self.job.experts.budget_mode)


def _level_at(levels, position: int):
    return jax.tree.map(lambda x: x[position], levels)


def _report(on_progress, works: dict[int, _BatchWork], slots: list[_LevelRun | None], config: PPOConfig) -> None:
    """Updates done per batch in progress: a level that is done counts its whole budget."""
    running = {(run.batch, run.position): len(run.success_rates) for run in slots if run is not None}
    for batch, work in works.items():
        done = sum(
            config.num_updates
            if params is not None
            else running.get((batch, position), 0) * config.select_every_updates
            for position, params in enumerate(work.params)
        )
        on_progress(batch, done, len(work.params) * config.num_updates)
