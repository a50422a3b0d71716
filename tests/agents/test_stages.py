"""Training in stages (separately compiled programs called from the host) gives `train_levels`'s output bit for bit."""

import dataclasses

import jax
import numpy as np
import pytest
from agents_test_helpers import ENV_PARAMS, STATIC, TRAIN_CONFIG, keys, mirrored_level, stack, thruster_level

from kforge.agents import EVALUATE, START, stage_functions, train_in_stages, train_levels

STAGED_CONFIG = dataclasses.replace(
    TRAIN_CONFIG, env_steps_per_level=TRAIN_CONFIG.num_envs * TRAIN_CONFIG.num_steps * 7, select_every_updates=3
)
"""7 updates, evaluated after 3, 6 and 7: two runs of 3 updates and a shorter last one."""


@pytest.mark.slow
def test_training_in_stages_equals_train_levels_bit_for_bit():
    levels, level_keys = stack(thruster_level(), mirrored_level()), keys(0, 1)
    whole = jax.device_get(train_levels(levels, level_keys, STAGED_CONFIG, ENV_PARAMS, STATIC))
    stages = {name: jax.jit(function) for name, function in stage_functions(STAGED_CONFIG, STATIC).items()}
    assert sorted(stages) == sorted([START, EVALUATE, "update_3", "update_1"])
    evaluated = []
    staged = jax.device_get(
        train_in_stages(stages, levels, level_keys, ENV_PARAMS, STAGED_CONFIG, on_evaluated=evaluated.append)
    )
    assert evaluated == [3, 6, 7]
    assert np.asarray(staged.selection.success_rate).shape == (2, 3)
    assert np.asarray(staged.metrics.success_rate).shape == (2, 7)
    assert jax.tree.structure(staged) == jax.tree.structure(whole)
    jax.tree.map(np.testing.assert_array_equal, staged, whole)
