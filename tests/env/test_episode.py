"""Episodes: goal reward, dense shaping, termination, frame skip and same-level auto-reset."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from kforge.engine import SceneBuilder, SimParams
from kforge.engine import step as physics_step
from kforge.env import ActionType, EnvParams, Role, StaticEnvParams, advance, noop_action, reset, step
from kforge.env.level_builder import build_level

STATIC = StaticEnvParams.for_size("m")
PARAMS = EnvParams()
NOOP = noop_action(ActionType.MULTI_DISCRETE)
GRAVITY = 9.81  # [m/s^2]
FLOOR_TOP = 0.4  # [m]


def _drop_level(lower_role: Role, gap: float = 0.35, lower_size: float = 0.3, upper_size: float = 0.3):
    """A green box `gap` metres above a box of `lower_role` resting on the floor."""
    scene = SceneBuilder(STATIC.sim)
    lower_top = FLOOR_TOP + lower_size
    lower = scene.add_box((2.5, FLOOR_TOP + lower_size / 2), (lower_size, lower_size))
    green = scene.add_box((2.5, lower_top + gap + upper_size / 2), (upper_size, upper_size))
    return build_level(scene, roles={green: Role.GREEN, lower: lower_role})


def _run_until_done(level, action=NOOP, params=PARAMS, static=STATIC, max_steps=256):
    state = reset(level)
    for t in range(1, max_steps + 1):
        previous = state
        state, result = step(state, action, level, params, static)
        if bool(result.done):
            return t, previous, result, state
    raise AssertionError("episode did not end")


def _fall_steps(gap: float) -> float:
    """Env steps for a free fall of `gap` metres from rest (2 physics steps of 1/60 s each)."""
    return math.sqrt(2 * gap / GRAVITY) / (STATIC.frame_skip * PARAMS.sim.dt)


def test_green_falling_on_blue_succeeds_when_it_lands():
    t, previous, result, _ = _run_until_done(_drop_level(Role.BLUE))
    assert bool(result.success) and not bool(result.failure) and not bool(result.truncated)
    assert abs(t - _fall_steps(0.35)) <= 1.0
    # Goal reward +1 plus shaping: the distance shrank by (old - new) metres during the step.
    old = float(jnp.linalg.norm(previous.sim.bodies.position[4] - previous.sim.bodies.position[5]))
    assert float(result.reward) == pytest.approx(
        1.0 - (float(result.distance) - old) * PARAMS.dense_reward_scale, abs=1e-5
    )


def test_green_falling_on_red_fails():
    _, _, result, _ = _run_until_done(_drop_level(Role.RED))
    assert bool(result.failure) and not bool(result.success)
    assert float(result.reward) == pytest.approx(-1.0, abs=1e-6)  # no blue: no distance, no shaping


def test_red_wins_over_blue_in_the_same_step():
    scene = SceneBuilder(STATIC.sim)
    blue = scene.add_circle((2.3, 0.6), 0.2, static=True)
    red = scene.add_circle((2.7, 0.6), 0.2, static=True)
    green = scene.add_box((2.5, 1.0), (0.6, 0.1))
    level = build_level(scene, roles={green: Role.GREEN, blue: Role.BLUE, red: Role.RED})
    _, _, result, _ = _run_until_done(level)
    assert bool(result.failure) and not bool(result.success)
    assert float(result.reward) < -0.9


def test_timeout_truncates_and_returns_to_the_start():
    static = StaticEnvParams.for_size("m", max_timesteps=12)
    scene = SceneBuilder(static.sim)
    green = scene.add_circle((1.0, FLOOR_TOP + 0.2), 0.2)
    blue = scene.add_circle((4.0, FLOOR_TOP + 0.2), 0.2)
    level = build_level(scene, roles={green: Role.GREEN, blue: Role.BLUE})
    t, _, result, state = _run_until_done(level, static=static)
    assert t == 12
    assert bool(result.truncated) and not bool(result.success) and not bool(result.failure)
    assert abs(float(result.reward)) < 1e-3
    jax.tree.map(np.testing.assert_array_equal, state, reset(level))


def test_state_continues_until_done_and_resets_exactly_after():
    level = _drop_level(Role.BLUE)
    state = reset(level)
    state, result = step(state, NOOP, level, PARAMS, STATIC)
    assert not bool(result.done) and int(state.timestep) == 1
    assert float(state.last_distance) == pytest.approx(float(result.distance))
    t, _, _, after = _run_until_done(level)
    assert t > 1
    jax.tree.map(np.testing.assert_array_equal, after, reset(level))
    assert int(after.timestep) == 0 and float(after.last_distance) == -1.0


def test_one_env_step_is_frame_skip_physics_steps_with_the_same_action():
    level = _drop_level(Role.BLUE, gap=1.5)
    state = reset(level)
    stepped, _ = advance(state, NOOP, PARAMS, STATIC, ActionType.MULTI_DISCRETE)
    sim = level.sim
    for _ in range(STATIC.frame_skip):
        sim, _ = physics_step(sim, SimParams(), jnp.zeros(2), jnp.zeros(2), static=STATIC.sim)
    # The same operations compiled into two programs (a scan inside the env step, a loop of jitted steps here): XLA
    # may fuse them differently, so float results agree to rounding; one physics step more or less moves the
    # falling disc by centimetres (atol: values that cancel to near zero, e.g. a resting body's spin).
    jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6), stepped.sim, sim)


def _thruster_level():
    scene = SceneBuilder(STATIC.sim)
    green = scene.add_circle((1.0, FLOOR_TOP + 0.2), 0.2)
    blue = scene.add_circle((4.0, FLOOR_TOP + 0.2), 0.2)
    scene.add_thruster(green, (1.0, FLOOR_TOP + 0.2), 0.0, power=0.5)
    return build_level(scene, roles={green: Role.GREEN, blue: Role.BLUE})


@pytest.mark.parametrize("scale", [0.1, 0.0])
def test_dense_shaping_rewards_the_distance_change(scale):
    level = _thruster_level()
    params = EnvParams(dense_reward_scale=scale)
    fire = jnp.asarray([0, 0, 0, 0, 1, 0])
    state = reset(level)
    rewards, distances = [], []
    for _ in range(6):
        state, result = step(state, fire, level, params, STATIC)
        rewards.append(float(result.reward))
        position = np.asarray(state.sim.bodies.position)
        distances.append(float(np.linalg.norm(position[6] - position[7])))
    assert rewards[0] == 0.0  # no previous distance after a reset
    expected = [-(after - before) * scale for before, after in zip(distances[:-1], distances[1:], strict=True)]
    np.testing.assert_allclose(rewards[1:], expected, atol=1e-6)
    if scale:
        assert all(r > 0 for r in rewards[1:])  # the thruster pushes green towards blue


def test_nan_ends_the_episode_as_unstable_with_a_finite_reward():
    level = _thruster_level()
    state = reset(level)
    state = state.replace(
        sim=state.sim.replace(bodies=state.sim.bodies.replace(velocity=state.sim.bodies.velocity.at[6, 0].set(jnp.nan)))
    )
    state = state.replace(last_distance=jnp.float32(3.0))
    after, result = step(state, NOOP, level, PARAMS, STATIC)
    assert bool(result.done) and bool(result.unstable) and not bool(result.success)
    assert np.isfinite(float(result.reward))
    jax.tree.map(np.testing.assert_array_equal, after, reset(level))


def test_vmapped_steps_equal_single_steps_on_mixed_levels():
    levels = [_drop_level(Role.BLUE), _drop_level(Role.RED, gap=0.1), _thruster_level()]
    batch = jax.tree.map(lambda *x: jnp.stack(x), *levels)
    actions = jnp.asarray([[0, 0, 0, 0, 1, 0]] * 3)
    states = jax.vmap(reset)(batch)
    batched_step = jax.jit(jax.vmap(lambda s, a, lv: step(s, a, lv, PARAMS, STATIC)))
    singles = [reset(level) for level in levels]
    for _ in range(12):
        states, results = batched_step(states, actions, batch)
        outs = [step(s, actions[i], levels[i], PARAMS, STATIC) for i, s in enumerate(singles)]
        singles = [o[0] for o in outs]
        for i, (single, single_result) in enumerate(outs):
            np.testing.assert_allclose(np.asarray(results.reward[i]), np.asarray(single_result.reward), atol=1e-6)
            assert bool(results.done[i]) == bool(single_result.done)
            np.testing.assert_allclose(
                np.asarray(states.sim.bodies.position[i]), np.asarray(single.sim.bodies.position), atol=1e-5
            )
