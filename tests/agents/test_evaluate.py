"""Evaluation from a level's start and from stored mid-episode states, with fixed policies and a trained expert."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from agents_test_helpers import (
    BLUE_X,
    ENV_PARAMS,
    GREEN_X,
    RADIUS,
    STATIC,
    THRUSTER_POWER,
    TRAIN_CONFIG,
    keys,
    stack,
    thruster_level,
)

from kforge.agents import EpisodePlan, evaluate, initial_params
from kforge.env import reset

EPISODES = 8
SURE_LOGIT = 30.0
"""Logit margin that makes a choice certain in float32."""

GREEN = 5  # body index of green in size s (polygon slots 0-4, then circles)


def _fixed_policy(fire: bool):
    """Parameters whose logits ignore the observation: thruster slot 4 always fires (or never does)."""
    params = initial_params(jax.random.PRNGKey(0), TRAIN_CONFIG, STATIC)
    output = params["params"]["actor_output"]
    bias = jnp.zeros_like(output["bias"]).at[13 if fire else 12].set(SURE_LOGIT)
    params["params"]["actor_output"] = {"kernel": jnp.zeros_like(output["kernel"]), "bias": bias}
    return params


def _evaluate(params, start_states=None, seed=0):
    levels = stack(thruster_level())
    batched = stack(params)
    plan = EpisodePlan(TRAIN_CONFIG, STATIC, EPISODES)
    return evaluate(batched, levels, keys(seed), plan, ENV_PARAMS, start_states=start_states)


def _acceleration() -> float:
    """[m/s^2] of green under constant thrust (frictionless disc of density 1)."""
    mass = math.pi * RADIUS**2
    return ENV_PARAMS.sim.base_thruster_power * THRUSTER_POWER / mass


def _env_steps_to_contact(gap: float, speed: float = 0.0) -> int:
    """Env steps until a disc at `speed`, accelerating under constant thrust, closes `gap` (semi-implicit Euler)."""
    dt, a = ENV_PARAMS.sim.dt, _acceleration()
    travelled, velocity, physics_steps = 0.0, speed, 0
    while travelled < gap:
        velocity += a * dt
        travelled += velocity * dt
        physics_steps += 1
    return math.ceil(physics_steps / STATIC.frame_skip)


def test_doing_nothing_never_succeeds_and_runs_to_the_time_limit():
    result = _evaluate(_fixed_policy(fire=False))
    assert float(result.success_rate[0]) == 0.0
    np.testing.assert_array_equal(result.lengths[0], STATIC.max_timesteps)
    np.testing.assert_allclose(result.returns[0], 0.0, atol=1e-5)  # green never moves: no shaping


def test_firing_all_the_time_reaches_blue_when_kinematics_say():
    result = _evaluate(_fixed_policy(fire=True))
    assert float(result.success_rate[0]) == 1.0
    expected = _env_steps_to_contact(BLUE_X - GREEN_X - 2 * RADIUS)
    assert expected < STATIC.max_timesteps
    assert np.all(np.abs(np.asarray(result.lengths[0]) - expected) <= 1)
    # +1 for success, plus 0.1 per metre of approach (centres end 2 radii apart; the first step is not shaped).
    approach = BLUE_X - GREEN_X - 2 * RADIUS
    np.testing.assert_allclose(result.returns[0], 1.0 + ENV_PARAMS.dense_reward_scale * approach, atol=0.02)


def _mid_episode_state(travelled: float, timestep: int):
    """The thruster level's state after green travelled `travelled` metres from rest under constant thrust."""
    start = reset(thruster_level())
    speed = math.sqrt(2 * _acceleration() * travelled)
    bodies = start.sim.bodies
    bodies = bodies.replace(
        position=bodies.position.at[GREEN, 0].add(travelled), velocity=bodies.velocity.at[GREEN, 0].set(speed)
    )
    distance = BLUE_X - GREEN_X - travelled
    return start.replace(
        sim=start.sim.replace(bodies=bodies), timestep=jnp.int32(timestep), last_distance=jnp.float32(distance)
    )


def test_evaluation_continues_a_stored_mid_episode_state():
    travelled = 1.5  # [m]
    state = _mid_episode_state(travelled, timestep=10)
    result = _evaluate(_fixed_policy(fire=True), start_states=stack(state))
    assert float(result.success_rate[0]) == 1.0
    gap = BLUE_X - GREEN_X - 2 * RADIUS - travelled
    expected = _env_steps_to_contact(gap, speed=float(state.sim.bodies.velocity[GREEN, 0]))
    assert expected < _env_steps_to_contact(BLUE_X - GREEN_X - 2 * RADIUS) - 10  # it starts with speed
    assert np.all(np.abs(np.asarray(result.lengths[0]) - expected) <= 1)
    # Shaping continues from the stored distance: the return counts only the remaining approach.
    np.testing.assert_allclose(result.returns[0], 1.0 + ENV_PARAMS.dense_reward_scale * gap, atol=0.02)


def test_evaluation_from_a_stored_state_keeps_its_time_limit():
    remaining = 3
    state = _mid_episode_state(0.5, timestep=STATIC.max_timesteps - remaining)
    result = _evaluate(_fixed_policy(fire=True), start_states=stack(state))
    assert float(result.success_rate[0]) == 0.0
    np.testing.assert_array_equal(result.lengths[0], remaining)


@pytest.mark.slow
def test_trained_expert_succeeds_in_evaluation(trained_mixed):
    plan = EpisodePlan(TRAIN_CONFIG, STATIC, num_episodes=64)
    levels = stack(thruster_level())
    expert = jax.tree.map(lambda x: x[:1], trained_mixed.params)
    trained = evaluate(expert, levels, keys(7), plan, ENV_PARAMS)
    assert float(trained.success_rate[0]) >= 0.9
    untrained = stack(initial_params(jax.random.PRNGKey(0), TRAIN_CONFIG, STATIC))
    before = evaluate(untrained, levels, keys(7), plan, ENV_PARAMS)
    assert float(before.success_rate[0]) <= 0.25  # measured 0.16: a near-uniform policy is mostly too slow
