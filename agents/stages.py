"""`train_levels` as separately compiled programs: start, a run of updates, an evaluation; a host loop calls them.

One program holding the whole training compiles the physics step twice (the rollout's and the evaluation's) in one
long, serial compilation. Split into stages, each compiles on its own (in parallel on several cores) and the
evaluation's program is called at every evaluation point. The stages compute what `train_levels` computes, in the
same order, with the same keys. Being other compiled programs, they may round otherwise in the last bits: equal on
the test's short training (tests/agents/test_stages.py), apart from about update 40 of the tiny scale on, so the
pipeline trains fixed budgets this way only (its data definition says so).

`stage_functions(config, static)` names the pure functions of a level batch (leading axis L on levels, keys and
trainings); `train_in_stages(stages, ...)` runs them, jitted or as compiled programs with the same signatures.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from kforge.agents.batching import check_level_keys, num_levels
from kforge.agents.config import PPOConfig
from kforge.agents.ppo import (
    SELECTION_STREAM,
    Selection,
    TrainOutput,
    _Best,
    _evaluation_program,
    _initial_carry,
    _TrainCarry,
    _update_program,
    initial_params,
)
from kforge.env import EnvParams, Level, StaticEnvParams

START = "start"
"""Stage (levels, keys) -> `BatchTraining` before the first update."""
EVALUATE = "evaluate"
"""Stage (levels, training, env_params, index, updates_done) -> (training, (success rate, mean return))."""


class BatchTraining(NamedTuple):
    """A level batch's training between stages (leading axis L on every leaf)."""

    carry: _TrainCarry  # parameters, optimiser and env states, training key
    best: _Best  # parameters of the best evaluation so far, its success rate and index
    selection_key: jax.Array  # key the evaluation episodes derive from


def update_stage(num_updates: int) -> str:
    """Name of the stage (levels, training, env_params) -> (training, metrics (L, num_updates)) of `num_updates`."""
    return f"update_{num_updates}"


def segments(config: PPOConfig) -> list[tuple[int, int]]:
    """(updates, updates done after them) of each run of updates before an evaluation, in order."""
    points = config.selection_updates
    return [(done - before, done) for before, done in zip((0, *points[:-1]), points, strict=True)]


def stage_functions(config: PPOConfig, static: StaticEnvParams) -> dict[str, Callable]:
    """The stages of training a level batch, by name (`START`, `update_stage(n)` for each run length n of
    `segments(config)`, `EVALUATE`); the arguments after the first two are shared by every level."""

    def start(levels: Level, keys: jax.Array) -> BatchTraining:
        """As `train_levels` starts: initial parameters drawn level after level (`lax.map`)."""
        split = jax.vmap(jax.random.split)(keys)
        params = jax.lax.map(lambda key: initial_params(key, config, static), split[:, 0])

        def one(level, level_params, key):
            return BatchTraining(
                carry=_initial_carry(level, level_params, key, config, static),
                best=_Best(level_params, jnp.array(-jnp.inf, jnp.float32), jnp.array(-1, jnp.int32)),
                selection_key=jax.random.fold_in(key, SELECTION_STREAM),
            )

        return jax.vmap(one)(levels, params, split[:, 1])

    def updates_of(num_updates: int) -> Callable:
        def update(levels: Level, training: BatchTraining, env_params: EnvParams):
            def one(level, level_training):
                carry, metrics = _update_program(level, config, env_params, static)(level_training.carry, num_updates)
                return level_training._replace(carry=carry), metrics

            return jax.vmap(one)(levels, training)

        return update

    def evaluate(levels: Level, training: BatchTraining, env_params: EnvParams, index, updates_done):
        def one(level, level_training):
            evaluate_and_keep = _evaluation_program(level, config, env_params, static)
            best, evaluation = evaluate_and_keep(
                level_training.carry.params, level_training.best, index, updates_done, level_training.selection_key
            )
            return level_training._replace(best=best), evaluation

        return jax.vmap(one)(levels, training)

    stages = {START: start, EVALUATE: evaluate}
    stages.update({update_stage(count): updates_of(count) for count, _ in segments(config)})
    return stages


def train_in_stages(
    stages: Mapping[str, Callable],
    levels: Level,
    keys: jax.Array,
    env_params: EnvParams,
    config: PPOConfig,
    on_evaluated: Callable[[int], None] | None = None,
) -> TrainOutput:
    """`train_levels(levels, keys, config, env_params, static)` by calling `stages` (the functions of
    `stage_functions(config, static)`, or programs compiled from them) from the host; `on_evaluated(updates_done)`
    is called after each evaluation."""
    check_level_keys(keys, num_levels(levels))
    training = stages[START](levels, keys)
    metrics, evaluations = [], []
    for index, (count, done) in enumerate(segments(config)):
        training, segment_metrics = stages[update_stage(count)](levels, training, env_params)
        training, evaluation = stages[EVALUATE](levels, training, env_params, np.int32(index), np.int32(done))
        metrics.append(segment_metrics)
        evaluations.append(evaluation)
        if on_evaluated is not None:
            on_evaluated(done)
    selection = Selection(
        env_steps=jnp.broadcast_to(
            jnp.asarray(config.selection_updates, jnp.int32) * config.steps_per_update,
            (num_levels(levels), len(evaluations)),
        ),
        success_rate=jnp.stack([success for success, _ in evaluations], axis=1),
        mean_return=jnp.stack([mean_return for _, mean_return in evaluations], axis=1),
        best=training.best.index,
    )
    return TrainOutput(
        params=training.best.params,
        metrics=jax.tree.map(lambda *runs: jnp.concatenate(runs, axis=1), *metrics),
        selection=selection,
    )
