"""Goal reward from contacts and the green-blue distance used for dense shaping."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from kforge.engine import StaticSimParams, pair_layout
from kforge.env.state import Role, Task

SUCCESS_REWARD = 1.0
"""Reward of a physics step in which green touches blue (and not red)."""

FAILURE_REWARD = -1.0
"""Reward of a physics step in which green touches red; wins over success in the same step."""


def goal_reward(touching: jnp.ndarray, task: Task, active: jnp.ndarray, static: StaticSimParams) -> jnp.ndarray:
    """() f32 reward of one physics step from its per-pair `touching` flags (K,): +1, -1 or 0."""
    layout = pair_layout(static)
    body_a, body_b = np.asarray(layout.body_a), np.asarray(layout.body_b)
    roles = jnp.where(active, task.roles, Role.DEFAULT)
    role_a, role_b = roles[body_a], roles[body_b]

    def pair_of(first: Role, second: Role) -> jnp.ndarray:
        return ((role_a == first) & (role_b == second)) | ((role_a == second) & (role_b == first))

    success = jnp.any(touching & pair_of(Role.GREEN, Role.BLUE))
    failure = jnp.any(touching & pair_of(Role.GREEN, Role.RED))
    return jnp.where(failure, FAILURE_REWARD, jnp.where(success, SUCCESS_REWARD, 0.0)).astype(jnp.float32)


def green_blue_distance(position: jnp.ndarray, active: jnp.ndarray, task: Task) -> jnp.ndarray:
    """() f32 [m] sum over (green, blue) shape pairs of their centre-to-centre distance."""
    green = active & (task.roles == Role.GREEN)
    blue = active & (task.roles == Role.BLUE)
    offsets = position[:, None, :] - position[None, :, :]
    distances = jnp.sqrt(jnp.sum(offsets**2, axis=-1))
    return jnp.sum(jnp.where(green[:, None] & blue[None, :], distances, 0.0))
