"""The PPO config: budget arithmetic, errors naming the keys at fault, and the YAML of defaults."""

from pathlib import Path

import pytest
import yaml

from kforge.agents import PPOConfig
from kforge.env.observations import ObservationType

pytestmark = pytest.mark.smoke

YAML_PATH = Path(__file__).resolve().parents[2] / "configs" / "ppo_specialist.yaml"


def test_num_updates_divides_the_budget_by_the_steps_per_update():
    config = PPOConfig(env_steps_per_level=1_000_000, num_envs=16, num_steps=125, num_minibatches=4)
    assert config.steps_per_update == 2000 and config.num_updates == 500 and config.minibatch_size == 500
    assert PPOConfig(env_steps_per_level=10_000_000, num_envs=16, num_steps=125).num_updates == 5000


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (dict(env_steps_per_level=1_000_000, num_envs=16, num_steps=128), "not a multiple of num_envs \\* num_steps"),
        (dict(env_steps_per_level=1000, num_envs=16, num_steps=125), "smaller than one update"),
        (dict(num_minibatches=3), "num_minibatches \\(3\\) does not divide"),
        (dict(num_envs=0), "num_envs must be a positive int"),
        (dict(gamma=1.5), "gamma must lie in"),
        (dict(learning_rate=0.0), "learning_rate must be > 0"),
        (dict(observation_type=ObservationType.PIXELS), "not supported"),
        (dict(select_every_updates=-1), "select_every_updates must be an int >= 0"),
        (dict(select_episodes=0), "select_episodes must be a positive int"),
    ],
)
def test_bad_configs_name_the_keys_at_fault(overrides, message):
    with pytest.raises(ValueError, match=message):
        PPOConfig(**overrides)


@pytest.mark.parametrize(
    ("budget", "every", "points"),
    [
        (1_000_000, 50, tuple(range(50, 501, 50))),  # 500 updates: every 100,000 env steps
        (48_000, 5, (5, 10, 15, 20, 24)),  # 24 updates: the last evaluation after the remainder
        (48_000, 0, (24,)),  # after the last update only
        (48_000, 100, (24,)),  # a period longer than training
    ],
)
def test_the_policy_is_evaluated_every_period_and_after_the_last_update(budget, every, points):
    config = PPOConfig(env_steps_per_level=budget, num_envs=16, num_steps=125, select_every_updates=every)
    assert config.selection_updates == points


def test_a_10m_budget_evaluates_every_point_a_1m_budget_does():
    one, ten = (PPOConfig(env_steps_per_level=budget) for budget in (1_000_000, 10_000_000))
    assert set(one.selection_updates) <= set(ten.selection_updates)


def test_from_mapping_rejects_unknown_keys_and_reads_observation_names():
    with pytest.raises(ValueError, match="unknown PPOConfig keys \\['lr'\\]"):
        PPOConfig.from_mapping({"lr": 1e-3})
    config = PPOConfig.from_mapping({"observation_type": "symbolic_flat", "num_envs": 8, "num_steps": 125})
    assert config.observation_type is ObservationType.SYMBOLIC_FLAT and config.num_envs == 8


def test_yaml_holds_the_defaults():
    values = yaml.safe_load(YAML_PATH.read_text())
    assert PPOConfig.from_mapping(values) == PPOConfig()
    assert set(values) == set(PPOConfig.__dataclass_fields__)
