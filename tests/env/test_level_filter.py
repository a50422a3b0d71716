"""Trivial-level filter and first-episode rollouts on hand-built size-s levels with known outcomes."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from kforge.engine import SceneBuilder
from kforge.env import EnvParams, Level, Role, StaticEnvParams, empty_task
from kforge.env.level_filter import FilterReason, filter_levels, goals_touching, has_actuator
from kforge.env.rollout import Outcome, Policy, first_episode_outcomes

STATIC = StaticEnvParams.for_size("s")
PARAMS = EnvParams()
FLOOR_TOP = 0.4  # [m]
GRAVITY = 9.81  # [m/s^2]
ENV_STEP = STATIC.frame_skip / 60.0  # [s]
BOX = 0.5  # [m] side of the blue box
BALL = 0.2  # [m] radius of the green ball
DROP = 1.0  # [m] gap between the falling ball and the box top


def _level(builder: SceneBuilder, roles: dict[int, Role]) -> Level:
    task = empty_task(STATIC.num_bodies, STATIC.sim.num_joints, STATIC.sim.num_thrusters)
    role_array = np.zeros(STATIC.num_bodies, np.int32)
    for body, role in roles.items():
        role_array[body] = role
    task = task.replace(roles=jnp.asarray(role_array), densities=jnp.asarray(builder.densities, jnp.float32))
    return Level(sim=builder.build(), task=task)


def _box_and_ball(ball_bottom: float, ball_x: float = 2.5, box_x: float = 2.5):
    builder = SceneBuilder(STATIC.sim)
    box = builder.add_box((box_x, FLOOR_TOP + BOX / 2), (BOX, BOX), static=True)
    ball = builder.add_circle((ball_x, ball_bottom + BALL), BALL)
    return builder, box, ball


def touching_level() -> Level:
    """Green ball resting on the blue box at t = 0 (with a thruster, so only the touch is trivial)."""
    builder, box, ball = _box_and_ball(FLOOR_TOP + BOX)
    builder.add_thruster(ball, (2.5, FLOOR_TOP + BOX + BALL), angle=math.pi / 2, power=1.0)
    return _level(builder, {box: Role.BLUE, ball: Role.GREEN})


def falling_level() -> Level:
    """Green ball DROP above the blue box: the no-op wins when it lands."""
    builder, box, ball = _box_and_ball(FLOOR_TOP + BOX + DROP)
    builder.add_thruster(ball, (2.5, FLOOR_TOP + BOX + DROP + BALL), angle=0.0, power=1.0)
    return _level(builder, {box: Role.BLUE, ball: Role.GREEN})


def unmotorised_level() -> Level:
    """Green ball far from the blue box; its only joint (to a second ball) has its motor off."""
    builder, box, ball = _box_and_ball(FLOOR_TOP, ball_x=1.0, box_x=4.0)
    wheel = builder.add_circle((1.0, FLOOR_TOP + 3 * BALL), BALL / 2)
    builder.add_revolute_joint(ball, wheel, (1.0, FLOOR_TOP + 2.5 * BALL), motor_speed=1.0, motor_power=1.0)
    return _level(builder, {box: Role.BLUE, ball: Role.GREEN})


def thruster_level() -> Level:
    """Green ball on the floor far from the blue box, with a thruster pushing it towards the box: needs control."""
    builder, box, ball = _box_and_ball(FLOOR_TOP, ball_x=1.0, box_x=4.0)
    builder.add_thruster(ball, (1.0, FLOOR_TOP + BALL), angle=0.0, power=3.0)
    return _level(builder, {box: Role.BLUE, ball: Role.GREEN})


LEVELS = (touching_level, falling_level, unmotorised_level, thruster_level)


@pytest.fixture(scope="module")
def levels() -> Level:
    built = [make() for make in LEVELS]
    return jax.tree.map(lambda *x: jnp.stack(x), *built)


@pytest.fixture(scope="module")
def noop_rollout(levels):
    # Called like `filter_levels` calls it, so the compiled rollout is shared.
    return first_episode_outcomes(levels, PARAMS, STATIC, Policy.NOOP, num_steps=None)


def test_filter_reasons(levels):
    result = filter_levels(levels, PARAMS, STATIC)
    expected = [
        FilterReason.TOUCHING_AT_START,
        FilterReason.SOLVED_BY_NOOP,
        FilterReason.NO_ACTUATOR,
        FilterReason.KEPT,
    ]
    assert np.asarray(result.reason).tolist() == [int(r) for r in expected]
    assert np.asarray(result.keep).tolist() == [False, False, False, True]
    assert np.asarray(result.touching_at_start).tolist() == [True, False, False, False]
    assert np.asarray(result.no_actuator).tolist() == [False, False, True, False]
    # The touching level is also won by the no-op at its first step.
    assert np.asarray(result.solved_by_noop).tolist() == [True, True, False, False]


def test_noop_outcomes_and_fall_time(noop_rollout):
    outcome, length = np.asarray(noop_rollout.outcome), np.asarray(noop_rollout.length)
    assert outcome.tolist() == [Outcome.SUCCESS, Outcome.SUCCESS, Outcome.TIMEOUT, Outcome.TIMEOUT]
    assert length[0] == 1
    assert length[2] == length[3] == STATIC.max_timesteps
    # Free fall over DROP: t = sqrt(2 h / g); the step-start contact test sees the landing within one env step.
    fall_steps = math.sqrt(2 * DROP / GRAVITY) / ENV_STEP
    assert fall_steps - 1 <= length[1] <= fall_steps + 2


def test_touch_needs_contact():
    """Lifting the ball 1 cm (beyond the 5 mm touch distance) removes the touch at start."""
    builder, box, ball = _box_and_ball(FLOOR_TOP + BOX + 0.01)
    lifted = _level(builder, {box: Role.BLUE, ball: Role.GREEN})
    touching = jax.jit(goals_touching, static_argnames="static")
    assert not bool(touching(lifted, PARAMS, STATIC))
    assert bool(touching(touching_level(), PARAMS, STATIC))


def test_actuator_kinds():
    assert bool(has_actuator(thruster_level()))
    assert not bool(has_actuator(unmotorised_level()))
    motorised = unmotorised_level()
    joints = motorised.sim.joints.replace(motor_on=jnp.ones_like(motorised.sim.joints.motor_on))
    assert bool(has_actuator(motorised.replace(sim=motorised.sim.replace(joints=joints))))
    auto = unmotorised_level()
    assert bool(has_actuator(auto.replace(task=auto.task.replace(motor_auto=jnp.ones_like(auto.task.motor_auto)))))


def test_random_policy_needs_key(levels):
    with pytest.raises(ValueError, match="PRNG key"):
        first_episode_outcomes(levels, PARAMS, STATIC, Policy.UNIFORM_RANDOM)
    with pytest.raises(ValueError, match="num_steps"):
        first_episode_outcomes(levels, PARAMS, STATIC, Policy.NOOP, num_steps=STATIC.max_timesteps + 1)
