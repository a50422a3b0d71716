"""A level batch is a pure function of (config, shard, batch): levels regenerate from their index alone."""

import jax
import numpy as np
import pytest
from pipeline_test_helpers import tiny_job

from kforge.pipeline.generation import resolve
from kforge.pipeline.generation.level_batch import (
    batch_level_indices,
    batches_per_shard,
    num_shards,
    run_level_batch,
    sample_batch,
)
from kforge.pipeline.storage import FILTERED_PREFIX, Outcome
from kforge.pipeline.storage.writer import MAX_CURVE_POINTS, learning_curves


@pytest.fixture(scope="module")
def job():
    return resolve(tiny_job("unused"))


def test_work_is_cut_into_fixed_shards_and_batches(job):
    assert num_shards(job) == 2 and batches_per_shard(job) == 2
    np.testing.assert_array_equal(batch_level_indices(job, 1, 1), [6, 7])


def test_a_level_is_the_same_whatever_batch_it_is_sampled_in(job):
    first = sample_batch(job, np.array([5, 6]))
    second = sample_batch(job, np.array([6, 0]))
    jax.tree.map(lambda a, b: np.testing.assert_array_equal(np.asarray(a)[1], np.asarray(b)[0]), first, second)
    assert not np.array_equal(np.asarray(first.sim.bodies.position[0]), np.asarray(first.sim.bodies.position[1]))


def test_level_batch_is_deterministic_and_outcomes_are_consistent(job):
    result = run_level_batch(job, 1, 1)
    again = run_level_batch(job, 1, 1)
    jax.tree.map(np.testing.assert_array_equal, result.states, again.states)
    np.testing.assert_array_equal(result.action, again.action)
    assert list(result.outcome) == list(again.outcome)
    np.testing.assert_array_equal(result.level_id, [6, 7])
    # The split has 6 levels: shard 1 holds levels 4..7, so its batch 1 (levels 6 and 7) is padding.
    assert list(result.outcome) == [Outcome.PADDING] * 2 and not result.kept.any()
    first = run_level_batch(job, 0, 0)
    for i, outcome in enumerate(first.outcome):
        assert outcome == Outcome.KEPT or outcome == Outcome.UNSOLVED or outcome.startswith(FILTERED_PREFIX), outcome
        done, success = first.done[i], first.success[i]
        window_ok = bool(done.any()) and bool(np.all(success[done]))
        assert (outcome == Outcome.KEPT) == (window_ok and not outcome.startswith(FILTERED_PREFIX))
    assert first.action.shape == (2, 24, 6) and first.expert_success_rate.shape == (2,)
    # The experts are the selected ones: trained to an evaluation point, rated by its episodes.
    config = job.ppo
    assert set(first.expert_env_steps) <= {update * config.steps_per_update for update in config.selection_updates}
    np.testing.assert_array_equal(np.mod(first.expert_success_rate * config.select_episodes, 1), 0)
    np.testing.assert_array_equal(first.curves.success_rate, first.curves.success_rate.astype(np.float32))
    assert first.curves.success_rate.shape == first.curves.mean_return.shape == (2, len(first.curves.env_steps))
    assert first.curves.env_steps[-1] == job.split.expert_budget
    assert set(first.seconds) == {"sample_and_filter", "train", "collect"} and min(first.seconds.values()) > 0


def test_learning_curves_average_runs_of_updates_skipping_updates_without_episodes():
    updates = MAX_CURVE_POINTS * 2 + 1  # 65 updates: the first group has 3, the others 2
    success = np.full((1, updates), np.nan)
    success[0, 0], success[0, 2] = 0.0, 1.0  # group 0 = updates 0..2 (update 1 saw no episode end)
    success[0, 3:] = np.arange(3, updates) % 2  # every later group is one 1 and one 0 (in some order)
    curves = learning_curves(success, -success, steps_per_update=10)
    assert curves.env_steps[0] == 30 and curves.env_steps[-1] == updates * 10 and len(curves.env_steps) == 32
    np.testing.assert_allclose(curves.success_rate[0], 0.5)
    np.testing.assert_allclose(curves.mean_return[0], -0.5)
    empty = learning_curves(np.full((2, 3), np.nan), np.full((2, 3), np.nan), steps_per_update=4)
    assert np.isnan(empty.success_rate).all() and empty.env_steps.tolist() == [4, 8, 12]
