"""Trivial-level filter: levels won at t = 0, levels nothing can control, and levels the no-op policy solves.

Kinetix down-weights levels a 64-step no-op rollout solves (docs/kinetix.md, the filter); here every reason is a
per-level flag, and the no-op rollout covers the full episode unless told otherwise.
"""

from __future__ import annotations

import enum
import functools

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from kforge.engine import manifolds, modes_collide, pair_layout, world_geometry
from kforge.env.params import EnvParams, StaticEnvParams
from kforge.env.rollout import Outcome, Policy, first_episode_outcomes
from kforge.env.state import Level, Role


class FilterReason(enum.IntEnum):
    """Why a level is dropped; when several apply, the lowest nonzero value is reported."""

    KEPT = 0
    TOUCHING_AT_START = 1  # green and blue touch before anything moves
    NO_ACTUATOR = 2  # no active motorised revolute joint and no active thruster
    SOLVED_BY_NOOP = 3  # doing nothing wins within the checked steps


@struct.dataclass
class FilterResult:
    """Per-level verdicts, shape (B,)."""

    keep: jnp.ndarray  # (B,) bool
    reason: jnp.ndarray  # (B,) i32 `FilterReason`
    touching_at_start: jnp.ndarray  # (B,) bool
    no_actuator: jnp.ndarray  # (B,) bool
    solved_by_noop: jnp.ndarray  # (B,) bool


def goals_touching(level: Level, params: EnvParams, static: StaticEnvParams) -> jnp.ndarray:
    """() bool: a green and a blue shape are closer than the engine's touch distance (the contact test of a step)."""
    layout = pair_layout(static.sim)
    bodies = level.sim.bodies
    a, b = np.asarray(layout.body_a), np.asarray(layout.body_b)
    margin = jnp.full((layout.num_pairs,), params.sim.touch_distance, jnp.float32)
    manifold = manifolds(world_geometry(bodies), layout, margin)
    present = manifold.valid & (bodies.active[a] & bodies.active[b])[:, None]
    touching = modes_collide(bodies.collision_mode[a], bodies.collision_mode[b]) & jnp.any(
        present & (manifold.separation < params.sim.touch_distance), -1
    )
    roles = level.task.roles
    goal_pair = ((roles[a] == Role.GREEN) & (roles[b] == Role.BLUE)) | (
        (roles[a] == Role.BLUE) & (roles[b] == Role.GREEN)
    )
    return jnp.any(touching & goal_pair)


def has_actuator(level: Level) -> jnp.ndarray:
    """() bool: an active revolute joint with its motor on (or automatic), or an active thruster, exists."""
    joints = level.sim.joints
    motor = joints.active & ~joints.is_fixed & (joints.motor_on | level.task.motor_auto)
    thruster_bodies_active = level.sim.bodies.active[level.sim.thrusters.body]
    return jnp.any(motor) | jnp.any(level.sim.thrusters.active & thruster_bodies_active)


@functools.partial(jax.jit, static_argnames="static")
def _start_checks(levels: Level, params: EnvParams, static: StaticEnvParams):
    touching = jax.vmap(goals_touching, in_axes=(0, None, None))(levels, params, static)
    return touching, ~jax.vmap(has_actuator)(levels)


def filter_levels(
    levels: Level, params: EnvParams, static: StaticEnvParams, noop_steps: int | None = None
) -> FilterResult:
    """Flag trivial levels of a batch: touching at start, no actuator, solved by `noop_steps` no-op env steps.

    `noop_steps` defaults to the full episode (`static.max_timesteps`); Kinetix's filter used 64. The no-op
    rollout is `first_episode_outcomes` (compiled once per batch shape and step count, shared with other callers).
    """
    touching, no_actuator = _start_checks(levels, params, static)
    rollout = first_episode_outcomes(levels, params, static, Policy.NOOP, num_steps=noop_steps)
    solved = rollout.outcome == Outcome.SUCCESS
    reason = jnp.where(
        touching,
        FilterReason.TOUCHING_AT_START,
        jnp.where(no_actuator, FilterReason.NO_ACTUATOR, jnp.where(solved, FilterReason.SOLVED_BY_NOOP, 0)),
    ).astype(jnp.int32)
    return FilterResult(
        keep=reason == FilterReason.KEPT,
        reason=reason,
        touching_at_start=touching,
        no_actuator=no_actuator,
        solved_by_noop=solved,
    )
