"""`benchmarks/ppo.py --learner`: the learner is timed on one update's samples of every level, and its share is the
learner's time for the call's updates over the training call's time."""

from __future__ import annotations

import jax
import pytest

from benchmarks import ppo
from kforge.agents import PPOConfig
from kforge.env import StaticEnvParams, observation_shape

CONFIG = PPOConfig(num_envs=4, num_steps=8, num_minibatches=2, update_epochs=3, env_steps_per_level=3 * 32)


def test_the_learner_program_takes_every_step_of_an_update_on_each_levels_own_batch():
    static = StaticEnvParams.for_size("s")
    program, (params, opt_state, batch, keys, mask) = ppo.learner_program(2, CONFIG, static)
    obs = observation_shape(static, CONFIG.observation_type)
    assert batch.obs.shape == (2, 32) + obs.shape and batch.action.shape == (2, 32, 6)
    learnt, new_state, terms = program(params, opt_state, batch, keys, mask)
    assert terms.total.shape == (2, 3, 2)  # levels, epochs, minibatches
    assert [int(count) for count in new_state[1][0].count] == [6, 6]  # one Adam step per minibatch of each epoch
    first = jax.tree.leaves(learnt)[0]
    assert not (first[0] == first[1]).all()  # each level its own parameters


def test_the_share_is_the_learners_time_for_every_update_over_the_training_calls(monkeypatch):
    seconds = {"train": 6.0, "learner": 0.5}  # the training call runs CONFIG's 3 updates

    def fake_best_times(functions, rounds):
        assert rounds == ppo.LEARNER_ROUNDS
        return [seconds["train"], seconds["learner"]]

    monkeypatch.setattr(ppo, "best_times_interleaved", fake_best_times)
    result = ppo.measure_learner(lambda: None, 1, CONFIG, StaticEnvParams.for_size("s"))
    assert result == pytest.approx(
        {"seconds_per_update": 0.5, "training_seconds_per_update": 2.0, "share_of_training": 0.25}
    )
