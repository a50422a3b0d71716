"""A level batch is a pure function of (config, shard, batch): levels regenerate from their index alone."""

import jax
import numpy as np
import pytest
from pipeline_test_helpers import tiny_job

from pipeline.level_batch import (
    FILTERED_PREFIX,
    PADDING,
    UNSOLVED,
    batch_level_indices,
    batches_per_shard,
    num_shards,
    run_level_batch,
    sample_batch,
)
from pipeline.writer import KEPT


@pytest.fixture(scope="module")
def job():
    return tiny_job("unused")


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
    assert list(result.outcome) == [PADDING] * 2 and not result.kept.any()
    first = run_level_batch(job, 0, 0)
    for i, outcome in enumerate(first.outcome):
        assert outcome == KEPT or outcome == UNSOLVED or outcome.startswith(FILTERED_PREFIX), outcome
        done, success = first.done[i], first.success[i]
        window_ok = bool(done.any()) and bool(np.all(success[done]))
        assert (outcome == KEPT) == (window_ok and not outcome.startswith(FILTERED_PREFIX))
    assert first.action.shape == (2, 24, 6) and first.expert_success_rate.shape == (2,)
