"""Kinetix's observations of an episode state: symbolic flat, symbolic flat padded, symbolic entity and pixels.

Every observation is a pure function of the `EnvState` (jit- and vmap-able). Feature order and meaning follow Kinetix
(`renderer_symbolic_common`, `renderer_symbolic_flat`, `renderer_symbolic_entity`); our engine's fields map onto
Kinetix's as follows:

- shape rows: the engine's unified body table, polygons (slots 0..P-1) then circles; density = `Task.densities`,
  role one-hot from `Task.roles`.
- polygon vertices: Kinetix lists them clockwise (boxes start at the top-left corner), ours are counter-clockwise,
  so Kinetix vertex k = our vertex n-1-k (the inverse of the importer's reversal, and for `SceneBuilder` boxes exactly
  Kinetix's top-left-first order); unused vertex slots read (-1, -1) as in Kinetix.
- joints: Kinetix's `rotation` = our `reference_angle`; `min_rotation`/`max_rotation` = our `lower_angle`/
  `upper_angle` (both relative to the reference angle in Jax2D and here); `a/b_relative_pos` = `anchor_a/b`.
- thrusters: Kinetix's `relative_position` = `anchor`, `rotation` = `angle` (thrust direction in the body frame).
- the entity attention channel "current contacts" reads the engine's contact cache: a pair is in contact when either
  of its cached points holds a feature (`ContactCache.feature != NO_FEATURE`). Unlike Jax2D's manifolds, the cache
  also holds speculative points (shapes within the step's contact margin) and never holds pairs the engine does not
  solve (joint-connected, both static, or filtered by collision mode).

Deviation from Kinetix: entity rows and indexes of inactive slots are zeroed (Kinetix leaves them raw and relies on
the masks), so no observation depends on what an inactive slot holds.
"""

from __future__ import annotations

import enum
import functools

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from kforge.engine import NO_FEATURE, empty_state, pair_layout
from kforge.env.params import NUM_MOTOR_BINDINGS, NUM_THRUSTER_BINDINGS, StaticEnvParams
from kforge.env.pixels import GRAVITY_SCALE, pixel_observation
from kforge.env.state import NUM_ROLES, EnvState, Level, empty_task, initial_state

FLAT_CLIP = 10.0
"""Symbolic flat observations are clipped to [-FLAT_CLIP, FLAT_CLIP] (after which NaN becomes 0)."""

ANGULAR_VELOCITY_SCALE = 10.0
"""[rad/s] the angular-velocity feature is tanh(omega / ANGULAR_VELOCITY_SCALE)."""

UNUSED_VERTEX = -1.0
"""Coordinate value of a polygon's unused vertex slot (triangles) in shape features."""

NUM_ENTITY_TYPES = 4
"""Entity kinds in the padded flat observation's type one-hot: polygon, circle, joint, thruster."""

NUM_ATTENTION_CHANNELS = 4
"""Entity attention channels: all shapes, joint-connected (multi-hop), joined directly (one-hop), in contact."""


class ObservationType(enum.Enum):
    SYMBOLIC_FLAT = "symbolic_flat"
    SYMBOLIC_FLAT_PADDED = "symbolic_flat_padded"
    SYMBOLIC_ENTITY = "symbolic_entity"
    PIXELS = "pixels"


@struct.dataclass
class EntityObservation:
    """Per-entity feature rows with masks, and the shape graph as attention masks (Kinetix `EntityObservation`)."""

    polygons: jnp.ndarray  # (P, 27) f32 shape features + gravity feature
    circles: jnp.ndarray  # (C, 19) f32
    joints: jnp.ndarray  # (2J, 22) f32: every joint seen from b (rows 0..J-1), then from a (rows J..2J-1)
    thrusters: jnp.ndarray  # (T, 8) f32
    polygon_mask: jnp.ndarray  # (P,) bool active slots
    circle_mask: jnp.ndarray  # (C,) bool
    joint_mask: jnp.ndarray  # (2J,) bool
    thruster_mask: jnp.ndarray  # (T,) bool
    attention_mask: jnp.ndarray  # (4, N, N) bool shape-to-shape channels (see NUM_ATTENTION_CHANNELS)
    joint_indexes: jnp.ndarray  # (2J, 2) i32 global (from, to) shape of each joint row; 0 for inactive joints
    thruster_indexes: jnp.ndarray  # (T,) i32 global shape of each thruster; 0 for inactive thrusters


# --------------------------------------------------------------------------- per-entity features
def _shape_features(state: EnvState) -> jnp.ndarray:
    """(N, 16) features shared by polygons and circles."""
    bodies = state.sim.bodies
    column = functools.partial(jnp.expand_dims, axis=1)
    return jnp.concatenate(
        [
            bodies.position,
            bodies.velocity,
            column(bodies.inverse_mass),
            column(bodies.inverse_inertia),
            column(state.task.densities),
            column(jnp.tanh(bodies.angular_velocity / ANGULAR_VELOCITY_SCALE)),
            jax.nn.one_hot(state.task.roles, NUM_ROLES),
            column(jnp.sin(bodies.rotation)),
            column(jnp.cos(bodies.rotation)),
            column(bodies.friction),
            column(bodies.restitution),
        ],
        axis=1,
    ).astype(jnp.float32)


def _kinetix_vertices(vertices: jnp.ndarray, n_vertices: jnp.ndarray) -> jnp.ndarray:
    """(N, 8) vertices in Kinetix's clockwise order (vertex k = ours n-1-k), unused slots UNUSED_VERTEX."""
    slot = jnp.arange(vertices.shape[1])
    source = jnp.clip(n_vertices[:, None] - 1 - slot[None, :], 0, vertices.shape[1] - 1)
    reordered = jnp.take_along_axis(vertices, source[:, :, None], axis=1)
    used = slot[None, :] < n_vertices[:, None]
    return jnp.where(used[:, :, None], reordered, UNUSED_VERTEX).reshape(vertices.shape[0], -1)


def _polygon_and_circle_features(state: EnvState, static: StaticEnvParams) -> tuple[jnp.ndarray, jnp.ndarray]:
    """Polygon rows (P, 26) and circle rows (C, 18), not masked."""
    p = static.sim.num_polygons
    bodies = state.sim.bodies
    base = _shape_features(state)
    polygons = jnp.concatenate(
        [
            base[:p],
            jnp.zeros((p, 1), jnp.float32),
            _kinetix_vertices(bodies.vertices[:p], bodies.n_vertices[:p]),
            (bodies.n_vertices[:p, None] <= 3).astype(jnp.float32),
        ],
        axis=1,
    )
    circles = jnp.concatenate(
        [base[p:], bodies.radius[p:, None], jnp.ones((static.sim.num_circles, 1), jnp.float32)], axis=1
    )
    return polygons, circles


def _joint_features(state: EnvState) -> tuple[jnp.ndarray, jnp.ndarray]:
    """(2J, 22) joint rows seen from b then from a, and their (from, to) global shape indexes (2J, 2)."""
    joints = state.sim.joints
    revolute = (~joints.is_fixed).astype(jnp.float32)[:, None]
    limits = joints.has_limits.astype(jnp.float32)
    reference = joints.reference_angle
    limit_features = jnp.stack(
        [
            jnp.sin(joints.lower_angle) * limits,
            jnp.cos(joints.lower_angle) * limits,
            jnp.sin(joints.upper_angle) * limits,
            jnp.cos(joints.upper_angle) * limits,
            (joints.lower_angle - reference) * limits,
            (joints.upper_angle - reference) * limits,
        ],
        axis=1,
    )
    motor_features = revolute * jnp.concatenate(
        [
            joints.motor_speed[:, None],
            joints.motor_power[:, None],
            joints.motor_on.astype(jnp.float32)[:, None],
            limits[:, None],
            jax.nn.one_hot(state.task.motor_bindings, NUM_MOTOR_BINDINGS),
            limit_features,
        ],
        axis=1,
    )

    def seen_from(from_anchor, to_anchor):
        return jnp.concatenate(
            [
                joints.active.astype(jnp.float32)[:, None],
                joints.is_fixed.astype(jnp.float32)[:, None],
                from_anchor,
                to_anchor,
                jnp.sin(reference)[:, None],
                jnp.cos(reference)[:, None],
                motor_features,
            ],
            axis=1,
        )

    rows = jnp.concatenate([seen_from(joints.anchor_b, joints.anchor_a), seen_from(joints.anchor_a, joints.anchor_b)])
    from_b = jnp.stack([joints.body_b, joints.body_a], axis=1)
    from_a = jnp.stack([joints.body_a, joints.body_b], axis=1)
    indexes = jnp.where(jnp.tile(joints.active, 2)[:, None], jnp.concatenate([from_b, from_a]), 0)
    return rows.astype(jnp.float32), indexes.astype(jnp.int32)


def _thruster_features(state: EnvState) -> jnp.ndarray:
    """(T, 8) thruster rows."""
    thrusters = state.sim.thrusters
    return jnp.concatenate(
        [
            thrusters.active.astype(jnp.float32)[:, None],
            thrusters.anchor,
            jax.nn.one_hot(state.task.thruster_bindings, NUM_THRUSTER_BINDINGS),
            jnp.sin(thrusters.angle)[:, None],
            jnp.cos(thrusters.angle)[:, None],
            thrusters.power[:, None],
        ],
        axis=1,
    ).astype(jnp.float32)


def _gravity_feature(state: EnvState) -> jnp.ndarray:
    return state.sim.gravity[1] / GRAVITY_SCALE


def _zero_inactive(rows: jnp.ndarray, active: jnp.ndarray) -> jnp.ndarray:
    return jnp.where(active[:, None], rows, 0.0)


# --------------------------------------------------------------------------- symbolic flat
def _flat_rows(state: EnvState, static: StaticEnvParams) -> list[jnp.ndarray]:
    """Masked flat rows: floor and free polygons, circles, joints (+ endpoint one-hots), thrusters (+ body one-hot)."""
    p, n, j = static.sim.num_polygons, static.sim.num_bodies, static.sim.num_joints
    active = state.sim.bodies.active
    polygons, circles = _polygon_and_circle_features(state, static)
    kept = np.r_[0, static.sim.num_reserved_static : p]  # walls and ceiling (slots 1..3) carry no information
    joint_rows, joint_indexes = _joint_features(state)
    joints = jnp.concatenate(
        [joint_rows[:j], jax.nn.one_hot(joint_indexes[:j, 0], n), jax.nn.one_hot(joint_indexes[:j, 1], n)], axis=1
    )
    thrusters = jnp.concatenate([_thruster_features(state), jax.nn.one_hot(state.sim.thrusters.body, n)], axis=1)
    return [
        _zero_inactive(polygons[kept], active[kept]),
        _zero_inactive(circles, active[p:]),
        _zero_inactive(joints, state.sim.joints.active),
        _zero_inactive(thrusters, state.sim.thrusters.active),
    ]


def _clip_and_clean(obs: jnp.ndarray) -> jnp.ndarray:
    return jnp.nan_to_num(jnp.clip(obs, -FLAT_CLIP, FLAT_CLIP), nan=0.0)


def symbolic_flat(state: EnvState, static: StaticEnvParams) -> jnp.ndarray:
    """(L,) f32, L = (P-3)*26 + C*18 + J*(22 + 2N) + T*(8 + N) + 1: all rows flattened, then the gravity feature."""
    rows = _flat_rows(state, static)
    obs = jnp.concatenate([row.reshape(-1) for row in rows] + [_gravity_feature(state)[None]])
    return _clip_and_clean(obs)


def symbolic_flat_padded(state: EnvState, static: StaticEnvParams) -> jnp.ndarray:
    """(P-3 + C + J + T, W + 5) f32: the flat rows right-padded to the widest (W), an entity-type one-hot, gravity."""
    rows = _flat_rows(state, static)
    width = max(row.shape[1] for row in rows)
    padded = jnp.concatenate([jnp.pad(row, ((0, 0), (0, width - row.shape[1]))) for row in rows])
    types = np.concatenate([np.full(row.shape[0], kind) for kind, row in enumerate(rows)])
    gravity = jnp.full((padded.shape[0], 1), _gravity_feature(state))
    obs = jnp.concatenate([padded, jax.nn.one_hot(types, NUM_ENTITY_TYPES), gravity], axis=1)
    return _clip_and_clean(obs)


# --------------------------------------------------------------------------- symbolic entity
def _contact_matrix(state: EnvState, static: StaticEnvParams) -> jnp.ndarray:
    """(N, N) bool: pairs with a cached contact point, at Kinetix's (row, column) of the pair.

    Kinetix marks polygon pairs and circle pairs at (lower, higher) index and polygon-circle pairs at (circle, polygon).
    """
    layout = pair_layout(static.sim)
    rows, cols = np.asarray(layout.body_a).copy(), np.asarray(layout.body_b).copy()
    circle_polygon = (rows < static.sim.num_polygons) & (cols >= static.sim.num_polygons)
    rows[circle_polygon], cols[circle_polygon] = cols[circle_polygon], rows[circle_polygon]
    in_contact = jnp.any(state.sim.contacts.feature != NO_FEATURE, axis=1)
    n = static.sim.num_bodies
    return jnp.zeros((n, n), bool).at[rows, cols].set(in_contact)


def _attention_mask(state: EnvState, static: StaticEnvParams, joint_indexes: jnp.ndarray) -> jnp.ndarray:
    """(4, N, N) bool: all shapes, joint-connected groups, direct joints, contacts; only between active shapes."""
    n = static.sim.num_bodies
    active = state.sim.bodies.active
    both_active = active[:, None] & active[None, :]
    joint_active = jnp.tile(state.sim.joints.active, 2)
    shapes = jnp.arange(n)
    from_hot = (joint_indexes[:, 0, None] == shapes) & joint_active[:, None]
    to_hot = joint_indexes[:, 1, None] == shapes
    one_hop = jnp.any(from_hot[:, :, None] & to_hot[:, None, :], axis=0)
    channels = jnp.stack([jnp.ones((n, n), bool), ~state.sim.collision_matrix, one_hop, _contact_matrix(state, static)])
    return channels & both_active[None]


def symbolic_entity(state: EnvState, static: StaticEnvParams) -> EntityObservation:
    """Per-entity rows (NaN/inf in the state replaced first, no clipping), masks and attention channels."""
    state = jax.tree.map(jnp.nan_to_num, state)
    p = static.sim.num_polygons
    active = state.sim.bodies.active
    gravity = _gravity_feature(state)
    polygons, circles = _polygon_and_circle_features(state, static)
    joint_rows, joint_indexes = _joint_features(state)
    joint_mask = jnp.tile(state.sim.joints.active, 2)
    thruster_mask = state.sim.thrusters.active

    def with_gravity(rows):
        return jnp.concatenate([rows, jnp.full((rows.shape[0], 1), gravity)], axis=1)

    return EntityObservation(
        polygons=_zero_inactive(with_gravity(polygons), active[:p]),
        circles=_zero_inactive(with_gravity(circles), active[p:]),
        joints=_zero_inactive(joint_rows, joint_mask),
        thrusters=_zero_inactive(_thruster_features(state), thruster_mask),
        polygon_mask=active[:p],
        circle_mask=active[p:],
        joint_mask=joint_mask,
        thruster_mask=thruster_mask,
        attention_mask=_attention_mask(state, static, joint_indexes),
        joint_indexes=joint_indexes,
        thruster_indexes=jnp.where(thruster_mask, state.sim.thrusters.body, 0).astype(jnp.int32),
    )


# --------------------------------------------------------------------------- dispatch
def observe(state: EnvState, static: StaticEnvParams, observation_type: ObservationType):
    """The observation of `state` of the given type (pure; `static` and `observation_type` are static under jit)."""
    if observation_type is ObservationType.SYMBOLIC_FLAT:
        return symbolic_flat(state, static)
    if observation_type is ObservationType.SYMBOLIC_FLAT_PADDED:
        return symbolic_flat_padded(state, static)
    if observation_type is ObservationType.SYMBOLIC_ENTITY:
        return symbolic_entity(state, static)
    if observation_type is ObservationType.PIXELS:
        return pixel_observation(state, static)
    raise ValueError(f"unknown observation type {observation_type!r}; expected an ObservationType")


def observation_shape(static: StaticEnvParams, observation_type: ObservationType):
    """Pytree of `jax.ShapeDtypeStruct` of the observation type at this static size (computes nothing)."""
    sim = static.sim
    level = Level(sim=empty_state(sim), task=empty_task(sim.num_bodies, sim.num_joints, sim.num_thrusters))
    return jax.eval_shape(lambda state: observe(state, static, observation_type), initial_state(level))
