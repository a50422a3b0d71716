"""PPO in segments, for adaptive budgets: a level's training advanced one evaluation period at a time.

A `LevelTraining` is everything a level's training carries from one segment to the next; `train_segments` advances
a batch of them (vmap over slots) by `PPOConfig.select_every_updates` updates and evaluates each. The host decides
between segments which levels stop and puts new ones in their slots (`start_level`). Every random choice of a level
derives from its own key, and no computation mixes slots, so a level's result does not depend on its slot or on
the levels beside it (for one slot count: XLA may round differently for another).

A segment draws the same rollouts, minibatches and evaluation episodes as `train_level` with the same key and
period; the parameters it reaches may differ from `train_level`'s in the last bits (another compiled program).
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp

from kforge.agents.config import PPOConfig
from kforge.agents.ppo import (
    SELECTION_STREAM,
    UpdateMetrics,
    _Best,
    _initial_carry,
    _segment_program,
    _TrainCarry,
    initial_params,
)
from kforge.env import EnvParams, Level, StaticEnvParams


class LevelTraining(NamedTuple):
    """A level's training between two segments."""

    carry: _TrainCarry  # parameters, optimiser and env states, training key
    best: _Best  # parameters of the best evaluation so far, its success rate and index
    selection_key: jax.Array  # key the evaluation episodes derive from
    segments_done: jnp.ndarray  # () i32 segments trained (the next evaluation's index)


class SegmentOutput(NamedTuple):
    """What one segment of a level did (`train_segments` adds a leading slot axis)."""

    metrics: UpdateMetrics  # leaves (select_every_updates,): the segment's learning curves
    success_rate: jnp.ndarray  # () f32 share of the evaluation episodes that succeeded
    mean_return: jnp.ndarray  # () f32 their mean undiscounted return


def check_segmented(config: PPOConfig) -> None:
    """Segments need an evaluation period that divides the updates (every segment has the same length)."""
    every = config.select_every_updates
    if every < 1 or config.num_updates % every:
        raise ValueError(
            f"training in segments needs select_every_updates (>= 1) dividing the {config.num_updates} updates of "
            f"the budget, got {every}"
        )


@functools.partial(jax.jit, static_argnames=("config", "static"))
def start_level(level: Level, key: jax.Array, config: PPOConfig, static: StaticEnvParams) -> LevelTraining:
    """A level's training before its first update, from its key (split as `train_level` splits it)."""
    init_key, run_key = jax.random.split(key)
    params = initial_params(init_key, config, static)
    return LevelTraining(
        carry=_initial_carry(level, params, run_key, config, static),
        best=_Best(params, jnp.array(-jnp.inf, jnp.float32), jnp.array(-1, jnp.int32)),
        selection_key=jax.random.fold_in(run_key, SELECTION_STREAM),
        segments_done=jnp.array(0, jnp.int32),
    )


def train_segment(
    level: Level, training: LevelTraining, config: PPOConfig, env_params: EnvParams, static: StaticEnvParams
) -> tuple[LevelTraining, SegmentOutput]:
    """`select_every_updates` PPO updates of one level, then an evaluation of its policy."""
    every = config.select_every_updates
    index = training.segments_done
    train_and_evaluate = _segment_program(level, config, env_params, static)
    carry, best, metrics, (success_rate, mean_return) = train_and_evaluate(
        training.carry, training.best, index, (index + 1) * every, training.selection_key, every
    )
    trained = LevelTraining(carry, best, training.selection_key, index + 1)
    return trained, SegmentOutput(metrics, success_rate, mean_return)


@functools.partial(jax.jit, static_argnames=("config", "static"))
def train_segments(
    levels: Level, trainings: LevelTraining, config: PPOConfig, env_params: EnvParams, static: StaticEnvParams
) -> tuple[LevelTraining, SegmentOutput]:
    """`train_segment` on every slot (leading axis S) of a batch of levels and their trainings."""
    return jax.vmap(lambda level, training: train_segment(level, training, config, env_params, static))(
        levels, trainings
    )


@jax.jit
def put_slot(batch, slot: jnp.ndarray, value):
    """`batch` (a tree with a leading slot axis) with `value` (the same tree without it) at index `slot`."""
    return jax.tree.map(lambda whole, one: whole.at[slot].set(one), batch, value)


def best_params(training: LevelTraining):
    """Parameters of the level's best evaluation so far (the expert)."""
    return training.best.params
