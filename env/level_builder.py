"""Host-side construction of a `Level` from an engine `SceneBuilder` and the task's roles and bindings."""

from __future__ import annotations

from collections.abc import Collection, Mapping

import jax.numpy as jnp
import numpy as np

from kforge.engine import SceneBuilder
from kforge.env.params import NUM_MOTOR_BINDINGS, NUM_THRUSTER_BINDINGS
from kforge.env.state import Level, Role, Task


def build_level(
    scene: SceneBuilder,
    roles: Mapping[int, Role],
    motor_bindings: Mapping[int, int] | None = None,
    thruster_bindings: Mapping[int, int] | None = None,
    motor_auto: Collection[int] = (),
) -> Level:
    """The level made of `scene`'s shapes, with `roles` by body index (others DEFAULT) and actuator bindings.

    Bindings are given by joint / thruster index; unlisted actuators are bound to slot 0 of their kind.
    """
    static = scene.static
    role_array = np.zeros(static.num_bodies, np.int32)
    for body, role in roles.items():
        _check_index("roles", body, static.num_bodies)
        role_array[body] = Role(role)
    motor_array = _bindings("motor_bindings", motor_bindings or {}, static.num_joints, NUM_MOTOR_BINDINGS)
    thruster_array = _bindings(
        "thruster_bindings", thruster_bindings or {}, static.num_thrusters, NUM_THRUSTER_BINDINGS
    )
    auto = np.zeros(static.num_joints, bool)
    for joint in motor_auto:
        _check_index("motor_auto", joint, static.num_joints)
        auto[joint] = True
    task = Task(
        roles=jnp.asarray(role_array),
        densities=jnp.asarray(scene.densities, jnp.float32),
        motor_bindings=jnp.asarray(motor_array),
        thruster_bindings=jnp.asarray(thruster_array),
        motor_auto=jnp.asarray(auto),
    )
    return Level(sim=scene.build(), task=task)


def _check_index(what: str, index: int, size: int) -> None:
    if not 0 <= index < size:
        raise ValueError(f"{what}: index {index} out of range [0, {size})")


def _bindings(what: str, given: Mapping[int, int], size: int, num_slots: int) -> np.ndarray:
    out = np.zeros(size, np.int32)
    for index, slot in given.items():
        _check_index(what, index, size)
        if not 0 <= slot < num_slots:
            raise ValueError(f"{what}[{index}]: slot {slot} out of range [0, {num_slots})")
        out[index] = slot
    return out
