"""Levels and episode state: an engine `SimState` plus the task layered on it (roles, bindings, densities)."""

from __future__ import annotations

import enum

import jax.numpy as jnp
from flax import struct

from kforge.engine import SimState


class Role(enum.IntEnum):
    """What a shape means to the task: make GREEN touch BLUE without GREEN touching RED."""

    DEFAULT = 0
    GREEN = 1
    BLUE = 2
    RED = 3


NUM_ROLES = len(Role)

NO_DISTANCE = -1.0
"""`EnvState.last_distance` value meaning "no previous distance" (first step after a reset)."""


@struct.dataclass
class Task:
    """The per-level meaning of a scene; fixed during an episode. Shapes follow the engine's global body order."""

    roles: jnp.ndarray  # (N,) i32 `Role` of each shape (polygons then circles)
    densities: jnp.ndarray  # (N,) f32 [kg/m^2] density each shape was built with (mass properties derive from it)
    motor_bindings: jnp.ndarray  # (J,) i32 in [0, 4): unified action slot driving each joint's motor
    thruster_bindings: jnp.ndarray  # (T,) i32 in [0, 2): unified action slot 4 + b firing each thruster
    motor_auto: jnp.ndarray  # (J,) bool: the joint's motor always runs at +1, whatever the action


@struct.dataclass
class Level:
    """A task instance: the initial simulator state and the task on top of it."""

    sim: SimState
    task: Task


@struct.dataclass
class EnvState:
    """Everything an episode needs to continue and to be observed: raw simulator state, task, counters."""

    sim: SimState
    task: Task
    timestep: jnp.ndarray  # () i32 env steps since the last reset
    last_distance: jnp.ndarray  # () f32 [m] green-blue distance after the previous env step; NO_DISTANCE after reset


def empty_task(num_bodies: int, num_joints: int, num_thrusters: int) -> Task:
    """Every shape DEFAULT with density 1, every actuator bound to slot 0, no auto motors."""
    return Task(
        roles=jnp.zeros((num_bodies,), jnp.int32),
        densities=jnp.ones((num_bodies,), jnp.float32),
        motor_bindings=jnp.zeros((num_joints,), jnp.int32),
        thruster_bindings=jnp.zeros((num_thrusters,), jnp.int32),
        motor_auto=jnp.zeros((num_joints,), bool),
    )


def initial_state(level: Level) -> EnvState:
    """The episode state at t = 0 of `level`."""
    return EnvState(
        sim=level.sim,
        task=level.task,
        timestep=jnp.zeros((), jnp.int32),
        last_distance=jnp.full((), NO_DISTANCE, jnp.float32),
    )
