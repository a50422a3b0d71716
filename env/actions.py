"""Action spaces and their translation into per-actuator engine actions; the level's action mask."""

from __future__ import annotations

import enum

import jax
import jax.numpy as jnp

from kforge.env.params import NUM_ACTION_SLOTS, NUM_MOTOR_BINDINGS, NUM_THRUSTER_BINDINGS
from kforge.env.state import EnvState, Level

MULTI_DISCRETE_SIZES = (3, 3, 3, 3, 2, 2)
"""Choices per unified slot: motors {0: off, 1: +1, 2: -1}, thrusters {0: off, 1: on}."""

MOTOR_CHOICE_VALUES = (0.0, 1.0, -1.0)
"""Motor action value of each multi-discrete motor choice."""

NUM_DISCRETE_ACTIONS = 2 * NUM_MOTOR_BINDINGS + 1 + NUM_THRUSTER_BINDINGS
"""Discrete(11): 0..7 = motor a // 2 at +1 (odd a) or -1 (even a), 8 = no-op, 9 and 10 = thruster 0 or 1 on."""

DISCRETE_NOOP = 2 * NUM_MOTOR_BINDINGS


class ActionType(enum.Enum):
    MULTI_DISCRETE = "multi_discrete"
    DISCRETE = "discrete"
    CONTINUOUS = "continuous"


def unified_action(action: jnp.ndarray, action_type: ActionType) -> jnp.ndarray:
    """(6,) f32 slot values: motors in [-1, 1], thrusters in [0, 1]."""
    if action_type is ActionType.MULTI_DISCRETE:
        motor = jnp.asarray(MOTOR_CHOICE_VALUES, jnp.float32)[action[:NUM_MOTOR_BINDINGS]]
        thruster = action[NUM_MOTOR_BINDINGS:].astype(jnp.float32)
        return jnp.concatenate([motor, thruster])
    if action_type is ActionType.DISCRETE:
        slot = jnp.arange(NUM_ACTION_SLOTS)
        is_motor = action < 2 * NUM_MOTOR_BINDINGS
        motor_value = jnp.where(action % 2 == 1, 1.0, -1.0)
        motor_part = jnp.where(is_motor & (slot == action // 2), motor_value, 0.0)
        thruster_slot = NUM_MOTOR_BINDINGS + action - (DISCRETE_NOOP + 1)
        thruster_part = jnp.where((action > DISCRETE_NOOP) & (slot == thruster_slot), 1.0, 0.0)
        return (motor_part + thruster_part).astype(jnp.float32)
    if action_type is ActionType.CONTINUOUS:
        action = action.astype(jnp.float32)
        return jnp.concatenate(
            [jnp.clip(action[:NUM_MOTOR_BINDINGS], -1.0, 1.0), jnp.clip(action[NUM_MOTOR_BINDINGS:], 0.0, 1.0)]
        )
    raise ValueError(f"unknown action type {action_type!r}")


def actuator_actions(state: EnvState, action: jnp.ndarray, action_type: ActionType) -> tuple[jnp.ndarray, jnp.ndarray]:
    """Per-joint motor actions (J,) in [-1, 1] and per-thruster actions (T,) in [0, 1] for the engine."""
    slots = unified_action(action, action_type)
    task = state.task
    motor = jnp.where(task.motor_auto, 1.0, slots[task.motor_bindings])
    thruster = slots[NUM_MOTOR_BINDINGS + task.thruster_bindings]
    return motor, thruster


def action_mask(level: Level | EnvState) -> jnp.ndarray:
    """(6,) bool: which unified slots can influence the level (Kinetix's `get_valid_action_mask`).

    Motor slot i is valid when an active revolute joint is bound to it (whether its motor is on is not checked);
    thruster slot 4 + k when an active thruster is bound to k.
    """
    joints, thrusters, task = level.sim.joints, level.sim.thrusters, level.task
    revolute = joints.active & ~joints.is_fixed
    motor_valid = jnp.any(revolute[:, None] & (task.motor_bindings[:, None] == jnp.arange(NUM_MOTOR_BINDINGS)), axis=0)
    thruster_valid = jnp.any(
        thrusters.active[:, None] & (task.thruster_bindings[:, None] == jnp.arange(NUM_THRUSTER_BINDINGS)), axis=0
    )
    return jnp.concatenate([motor_valid, thruster_valid])


def noop_action(action_type: ActionType) -> jnp.ndarray:
    """The action that leaves every actuator off (auto motors still run)."""
    if action_type is ActionType.MULTI_DISCRETE:
        return jnp.zeros((NUM_ACTION_SLOTS,), jnp.int32)
    if action_type is ActionType.DISCRETE:
        return jnp.asarray(DISCRETE_NOOP, jnp.int32)
    return jnp.zeros((NUM_ACTION_SLOTS,), jnp.float32)


def random_action(key: jax.Array, action_type: ActionType) -> jnp.ndarray:
    """A uniformly random action of the space."""
    if action_type is ActionType.MULTI_DISCRETE:
        return jax.random.randint(key, (NUM_ACTION_SLOTS,), 0, jnp.asarray(MULTI_DISCRETE_SIZES), jnp.int32)
    if action_type is ActionType.DISCRETE:
        return jax.random.randint(key, (), 0, NUM_DISCRETE_ACTIONS, jnp.int32)
    low = jnp.asarray([-1.0] * NUM_MOTOR_BINDINGS + [0.0] * NUM_THRUSTER_BINDINGS)
    return jax.random.uniform(key, (NUM_ACTION_SLOTS,), jnp.float32, low, 1.0)
