"""The programs a level batch runs, compiled ahead of their first call (the collection program before any expert is
trained, from the shapes of fresh parameters), compute what the plain functions compute, bit for bit."""

import jax
import numpy as np
import pytest
from pipeline_test_helpers import tiny_job

from kforge.agents import WindowPlan, collect_windows, initial_params
from kforge.pipeline.generation import resolve
from kforge.pipeline.generation.level_batch import (
    KeyPurpose,
    batch_level_indices,
    level_keys,
    sample_batch,
    windows_successful,
)
from kforge.pipeline.generation.level_batch import _windows as level_batch_windows


@pytest.fixture(scope="module")
def job():
    return resolve(tiny_job("unused"))


def test_the_collection_program_compiled_ahead_rolls_out_what_collect_windows_does(job):
    env_params, static, config = job.env_params, job.static, job.ppo
    indices = batch_level_indices(job, 0, 0)
    levels = sample_batch(job, indices)
    params = jax.vmap(lambda key: initial_params(key, config, static))(
        jax.random.split(jax.random.key(3), len(indices))
    )
    window = level_batch_windows(job, params, levels, indices)
    expected = collect_windows(
        params,
        levels,
        level_keys(job.split.seed, indices, KeyPurpose.COLLECT),
        WindowPlan(config, static, num_steps=job.collect.window_steps, greedy=job.collect.greedy),
        env_params,
    )
    jax.tree.map(np.testing.assert_array_equal, window, expected)
    assert window.actions.shape == (len(indices), job.collect.window_steps, 6)
    np.testing.assert_array_equal(windows_successful(job, params, levels, indices), expected.successful)
