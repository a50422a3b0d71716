"""Which body pairs may collide: joints and collision modes."""

from __future__ import annotations

import jax.numpy as jnp

from kforge.engine.state import Joints


def joint_collision_matrix(joints: Joints, num_bodies: int) -> jnp.ndarray:
    """(N, N) bool: False for pairs in one joint-connected group (and the diagonal), True otherwise."""
    one_hot_a = (joints.body_a[:, None] == jnp.arange(num_bodies)) & joints.active[:, None]
    one_hot_b = (joints.body_b[:, None] == jnp.arange(num_bodies)) & joints.active[:, None]
    adjacency = one_hot_a.T.astype(jnp.int32) @ one_hot_b.astype(jnp.int32)
    reach = (adjacency + adjacency.T + jnp.eye(num_bodies, dtype=jnp.int32)) > 0
    # Transitive closure by repeated squaring: paths of length up to 2^k after k squarings.
    for _ in range(max(1, (num_bodies - 1).bit_length())):
        reach = (reach.astype(jnp.int32) @ reach.astype(jnp.int32)) > 0
    return ~reach


def modes_collide(mode_a, mode_b):
    """Kinetix collision modes: 0 hits only mode 2, 1 hits modes 1 and 2, 2 hits every mode."""
    return (mode_a == 2) | (mode_b == 2) | ((mode_a == 1) & (mode_b == 1))
