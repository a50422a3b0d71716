"""PPO fine-tuning from a behaviour-cloning policy: the BC network as the actor, its parameters as the start, and the
same training randomness as a run from fresh parameters."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from agents_test_helpers import ENV_PARAMS, STATIC, TRAIN_CONFIG, keys, mirrored_level, stack, thruster_level

from kforge.agents import (
    Architecture,
    EpisodePlan,
    NetworkConfig,
    PPOConfig,
    evaluate,
    initial_params,
    make_bc_network,
    train_levels,
    with_bc_actor,
)
from kforge.agents.networks import make_network
from kforge.env import ObservationType, observation_shape

BC_NETWORK = NetworkConfig(architecture=Architecture.MLP, hidden_size=32, num_hidden_layers=2)
FINE_TUNE_CONFIG = dataclasses.replace(TRAIN_CONFIG, actor=BC_NETWORK, env_steps_per_level=16 * 32 * 6)
"""Six updates, then one evaluation, with the BC MLP as the actor."""
FIRE_LOGIT = 13
"""The first thruster's slot (slot 4: logits 12 and 13) choosing to fire."""
FIRE_BIAS = 10.0
"""Added to the firing logit of a hand-made BC policy: it fires with probability 1 - e^-10."""


def _bc_params(fire: bool):
    obs = observation_shape(STATIC, ObservationType.SYMBOLIC_FLAT)
    params = make_bc_network(BC_NETWORK).init(jax.random.PRNGKey(7), jnp.zeros(obs.shape, obs.dtype))
    if not fire:
        return params
    last = max(name for name in params["params"] if name.startswith("Dense_"))
    bias = params["params"][last]["bias"].at[FIRE_LOGIT].add(FIRE_BIAS)
    return {"params": {**params["params"], last: {**params["params"][last], "bias": bias}}}


def _warm_params(fire: bool, count: int):
    fresh = initial_params(jax.random.PRNGKey(3), FINE_TUNE_CONFIG, STATIC)
    warm = with_bc_actor(fresh, _bc_params(fire))
    return jax.tree.map(lambda x: jnp.broadcast_to(x, (count,) + x.shape), warm)


def test_the_actor_plays_as_the_bc_policy_does():
    bc = _bc_params(fire=False)
    warm = with_bc_actor(initial_params(jax.random.PRNGKey(3), FINE_TUNE_CONFIG, STATIC), bc)
    obs = jax.random.normal(
        jax.random.PRNGKey(0), (5,) + observation_shape(STATIC, ObservationType.SYMBOLIC_FLAT).shape
    )
    logits, values = make_network(FINE_TUNE_CONFIG).apply(warm, obs)
    np.testing.assert_array_equal(np.asarray(logits), np.asarray(make_bc_network(BC_NETWORK).apply(bc, obs)))
    assert values.shape == (5,)


def test_bc_parameters_of_another_network_are_refused():
    other = NetworkConfig(architecture=Architecture.MLP, hidden_size=16, num_hidden_layers=2)
    obs = observation_shape(STATIC, ObservationType.SYMBOLIC_FLAT)
    bc = make_bc_network(other).init(jax.random.PRNGKey(7), jnp.zeros(obs.shape, obs.dtype))
    with pytest.raises(ValueError, match="do not fit PPOConfig.actor"):
        with_bc_actor(initial_params(jax.random.PRNGKey(3), FINE_TUNE_CONFIG, STATIC), bc)
    with pytest.raises(ValueError, match="no 'bc_actor' network"):
        with_bc_actor(initial_params(jax.random.PRNGKey(3), TRAIN_CONFIG, STATIC), bc)


def test_a_transformer_actor_is_refused_on_flat_observations():
    with pytest.raises(ValueError, match="a transformer reads symbolic_entity observations"):
        PPOConfig(actor=NetworkConfig(architecture=Architecture.TRANSFORMER))


def test_an_actor_is_read_from_plain_values():
    config = PPOConfig.from_mapping({"actor": {"architecture": "mlp", "hidden_size": 32, "num_hidden_layers": 2}})
    assert config.actor == BC_NETWORK


@pytest.mark.slow
def test_fine_tuning_starts_from_a_bc_policy_that_solves_the_level():
    """A BC policy that always fires solves the thruster level (firing all the time reaches blue in about 27 of 34
    steps), and PPO fine-tuned from it still does after six updates; the same network from fresh parameters (near
    uniform: it fires half the time and mostly runs out of time; about 0.28 measured) does not at the start."""
    levels = stack(thruster_level(), thruster_level())
    plan = EpisodePlan(FINE_TUNE_CONFIG, STATIC, num_episodes=16)
    warm = _warm_params(fire=True, count=2)
    assert np.all(np.asarray(evaluate(warm, levels, keys(4, 5), plan, ENV_PARAMS).success_rate) >= 0.9)
    fresh = evaluate(_warm_params(fire=False, count=2), levels, keys(4, 5), plan, ENV_PARAMS)
    assert np.all(np.asarray(fresh.success_rate) <= 0.5)
    tuned = train_levels(levels, keys(0, 1), FINE_TUNE_CONFIG, ENV_PARAMS, STATIC, warm)
    assert np.all(np.asarray(tuned.selection.success_rate)[:, 0] >= 0.9)


@pytest.mark.slow
def test_given_fresh_parameters_train_as_the_drawn_ones(trained_mixed):
    """`train_levels` from the parameters it would draw itself gives the same run bit for bit: a fine-tuned level and
    its fresh twin share the training randomness and differ only in where they start."""
    split = jax.vmap(jax.random.split)(keys(0, 1))
    drawn = jax.lax.map(lambda key: initial_params(key, TRAIN_CONFIG, STATIC), split[:, 0])
    given = train_levels(stack(thruster_level(), mirrored_level()), keys(0, 1), TRAIN_CONFIG, ENV_PARAMS, STATIC, drawn)
    jax.tree.map(np.testing.assert_array_equal, given.params, trained_mixed.params)
    jax.tree.map(np.testing.assert_array_equal, given.metrics, trained_mixed.metrics)
