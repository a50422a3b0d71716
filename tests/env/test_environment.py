"""The gymnax-style `Environment` returns the observation of the state it returns, and auto-resets."""

import jax
import jax.numpy as jnp
import numpy as np

from kforge.engine import SceneBuilder
from kforge.env import Environment, EnvParams, ObservationType, Role, reset, step
from kforge.env.level_builder import build_level


def test_environment_observes_the_state_it_returns():
    env = Environment.for_size("s")
    scene = SceneBuilder(env.static.sim)
    green = scene.add_circle((1.0, 0.6), 0.2)
    blue = scene.add_circle((4.0, 0.6), 0.2)
    scene.add_thruster(green, (1.0, 0.6), 0.0, power=0.5)
    level = build_level(scene, roles={green: Role.GREEN, blue: Role.BLUE})

    obs, state = env.reset(level)
    assert obs.shape == (140,)
    jax.tree.map(np.testing.assert_array_equal, state, reset(level))
    action = jnp.asarray([0, 0, 0, 0, 1, 0])
    obs, next_state, result = env.step(state, action, level, EnvParams())
    expected_state, expected_result = step(state, action, level, EnvParams(), env.static)
    jax.tree.map(np.testing.assert_array_equal, next_state, expected_state)
    np.testing.assert_array_equal(np.asarray(result.reward), np.asarray(expected_result.reward))
    np.testing.assert_array_equal(np.asarray(obs), np.asarray(env.observe(expected_state)))
    np.testing.assert_array_equal(np.asarray(env.action_mask(level)), [False] * 4 + [True, False])


def test_environment_is_a_static_jit_argument_per_configuration():
    small = Environment.for_size("s")
    assert small == Environment.for_size("s") and hash(small) == hash(Environment.for_size("s"))
    assert small != Environment.for_size("s", observation_type=ObservationType.PIXELS)
