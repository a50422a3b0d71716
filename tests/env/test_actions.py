"""Action spaces map to the documented slot values; bindings, auto motors and the action mask follow the level."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from kforge.engine import SceneBuilder
from kforge.env import (
    MULTI_DISCRETE_SIZES,
    ActionType,
    Role,
    StaticEnvParams,
    action_mask,
    noop_action,
    random_action,
    reset,
)
from kforge.env.actions import NUM_DISCRETE_ACTIONS, actuator_actions, unified_action
from kforge.env.level_builder import build_level

pytestmark = pytest.mark.smoke

M_STATIC = StaticEnvParams.for_size("m")


@pytest.mark.parametrize(
    ("action", "expected"),
    [
        ([0, 0, 0, 0, 0, 0], [0, 0, 0, 0, 0, 0]),
        ([1, 2, 0, 1, 1, 0], [1, -1, 0, 1, 1, 0]),
        ([2, 2, 2, 2, 1, 1], [-1, -1, -1, -1, 1, 1]),
    ],
)
def test_multi_discrete_slot_values(action, expected):
    got = unified_action(jnp.asarray(action, jnp.int32), ActionType.MULTI_DISCRETE)
    np.testing.assert_array_equal(np.asarray(got), np.asarray(expected, np.float32))


DISCRETE_TABLE = {
    0: [-1, 0, 0, 0, 0, 0],
    1: [1, 0, 0, 0, 0, 0],
    2: [0, -1, 0, 0, 0, 0],
    3: [0, 1, 0, 0, 0, 0],
    4: [0, 0, -1, 0, 0, 0],
    5: [0, 0, 1, 0, 0, 0],
    6: [0, 0, 0, -1, 0, 0],
    7: [0, 0, 0, 1, 0, 0],
    8: [0, 0, 0, 0, 0, 0],
    9: [0, 0, 0, 0, 1, 0],
    10: [0, 0, 0, 0, 0, 1],
}


def test_discrete_table_covers_every_action():
    assert sorted(DISCRETE_TABLE) == list(range(NUM_DISCRETE_ACTIONS))
    for action, expected in DISCRETE_TABLE.items():
        got = unified_action(jnp.asarray(action, jnp.int32), ActionType.DISCRETE)
        np.testing.assert_array_equal(np.asarray(got), np.asarray(expected, np.float32), err_msg=f"action {action}")


def test_continuous_is_clipped_per_slot_kind():
    got = unified_action(jnp.asarray([-3.0, 0.5, 2.0, -0.25, -1.0, 7.0]), ActionType.CONTINUOUS)
    np.testing.assert_allclose(np.asarray(got), [-1.0, 0.5, 1.0, -0.25, 0.0, 1.0])


@pytest.mark.parametrize("action_type", list(ActionType))
def test_noop_moves_nothing(action_type):
    np.testing.assert_array_equal(np.asarray(unified_action(noop_action(action_type), action_type)), np.zeros(6))


def test_random_actions_stay_in_their_spaces():
    keys = jax.random.split(jax.random.key(0), 2000)
    multi = np.asarray(jax.vmap(lambda k: random_action(k, ActionType.MULTI_DISCRETE))(keys))
    assert multi.min() == 0
    np.testing.assert_array_equal(multi.max(axis=0), np.asarray(MULTI_DISCRETE_SIZES) - 1)
    discrete = np.asarray(jax.vmap(lambda k: random_action(k, ActionType.DISCRETE))(keys))
    assert set(discrete.tolist()) == set(range(NUM_DISCRETE_ACTIONS))
    continuous = np.asarray(jax.vmap(lambda k: random_action(k, ActionType.CONTINUOUS))(keys))
    assert continuous[:, :4].min() >= -1 and continuous[:, 4:].min() >= 0 and continuous.max() <= 1


def _two_joint_level(*, second_fixed=False, second_active=True, motor_on=False, thruster_binding=1, motor_auto=()):
    scene = SceneBuilder(M_STATIC.sim)
    base = scene.add_box((2.0, 1.0), (0.6, 0.3))
    arm = scene.add_box((2.6, 1.0), (0.6, 0.1))
    wheel = scene.add_circle((1.4, 1.0), 0.2)
    scene.add_revolute_joint(base, arm, (2.3, 1.0), motor_speed=1.0, motor_power=1.0, motor_on=motor_on)
    if second_active:
        if second_fixed:
            scene.add_fixed_joint(base, wheel, (1.7, 1.0))
        else:
            scene.add_revolute_joint(base, wheel, (1.7, 1.0), motor_on=True, motor_speed=1.0, motor_power=1.0)
    scene.add_thruster(base, (2.0, 1.0), 0.0)
    return build_level(
        scene,
        roles={base: Role.GREEN, wheel: Role.BLUE},
        motor_bindings={0: 2, 1: 3},
        thruster_bindings={0: thruster_binding},
        motor_auto=motor_auto,
    )


def test_action_mask_marks_bound_revolute_joints_and_thrusters():
    mask = np.asarray(action_mask(_two_joint_level()))
    # motor_on is not checked (Kinetix): joint 0 is off but its slot 2 still counts.
    np.testing.assert_array_equal(mask, [False, False, True, True, False, True])


def test_action_mask_ignores_fixed_and_inactive_joints():
    np.testing.assert_array_equal(
        np.asarray(action_mask(_two_joint_level(second_fixed=True))), [False, False, True, False, False, True]
    )
    np.testing.assert_array_equal(
        np.asarray(action_mask(_two_joint_level(second_active=False, thruster_binding=0))),
        [False, False, True, False, True, False],
    )


def test_actuator_actions_follow_bindings_and_auto_motors():
    level = _two_joint_level(motor_auto=(1,))
    state = reset(level)
    motor, thruster = actuator_actions(state, jnp.asarray([0, 0, 2, 0, 0, 1]), ActionType.MULTI_DISCRETE)
    # Joint 0 is bound to slot 2 (choice 2 = -1); joint 1 is automatic (+1) whatever slot 3 says.
    np.testing.assert_array_equal(np.asarray(motor), [-1.0, 1.0])
    # Thruster 0 is bound to slot 5 (on); the unused thruster slot 1 reads slot 4 (off).
    np.testing.assert_array_equal(np.asarray(thruster), [1.0, 0.0])
