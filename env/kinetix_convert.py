"""Field mapping between a decoded Kinetix level (Jax2D field names, per-kind numpy arrays) and our env types;
the level functions also map batches of levels (arrays with leading batch axes).

Conventions (Jax2D 1.0.2 `sim_state.py`, `joint.py`, `engine.py`, checked against our engine):
- Global shape index: polygon i -> i, circle i -> P + i, in both; joint and thruster indices copy over unchanged.
- Jax2D stores polygon vertices clockwise, ours counter-clockwise: the first `n_vertices` points are reversed.
- A body's position is the point its vertices, joint anchors and thruster offsets are relative to and the point it
  rotates about: Jax2D's "centroid" (the vertex average, equal to the area centroid for triangles and parallelograms).
  It is kept as is, together with the file's inverse mass and inertia, so a level moves as it was designed in
  Kinetix (which uses I = m r^2 / 4 for discs and 2/3 of the true inertia for triangles).
- Joints: Jax2D `rotation` is the relative angle rot_b - rot_a at which the joint angle is zero (our
  `reference_angle`); `min_rotation` / `max_rotation` bound the same joint angle (our `lower_angle` / `upper_angle`);
  motors drive angular_velocity_b - angular_velocity_a toward motor_speed * base_motor_speed * action in both.
- Thrusters: Jax2D `rotation` is the thrust direction in the body frame (0 = body +x), our `angle`.
- Fields our engine has no use for (circle vertices, polygon radius, `highlighted`, joint warm-start impulses, the
  contact manifolds) are dropped on import and written with Kinetix's defaults on export; the joint and thruster
  `global_position` caches are recomputed on export.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from kforge.engine import SimParams, SimState, StaticSimParams, empty_state, joint_collision_matrix, rotate_host
from kforge.env.params import EnvParams, StaticEnvParams
from kforge.env.state import Level, Task

NUM_BOUNDARY_POLYGONS = 4
"""Kinetix's `num_static_fixated_polys`: polygon slots 0-3 hold the floor, the walls and the ceiling."""

MAX_VERTICES = 4
"""Kinetix's `max_polygon_vertices`: every polygon record holds this many vertices."""

SIM_PARAM_FIELDS: dict[str, str] = {
    "dt": "dt",
    "base_motor_speed": "base_motor_speed",
    "base_motor_power": "base_motor_power",
    "base_thruster_power": "base_thruster_power",
    "base_friction": "base_friction",
    "clip_position": "max_position",
    "clip_velocity": "max_velocity",
    "clip_angular_velocity": "max_angular_velocity",
}
"""Kinetix env_params key -> our `SimParams` field with the same meaning and unit."""

KINETIX_UNMODELLED_ENV_PARAMS: dict[str, float | int] = {
    "slop": 0.01,
    "baumgarte_coefficient_joints_v": 2.0,
    "baumgarte_coefficient_joints_p": 0.7,
    "baumgarte_coefficient_fjoint_av": 2.0,
    "baumgarte_coefficient_rjoint_limit_av": 5.0,
    "baumgarte_coefficient_collision": 0.2,
    "joint_stiffness": 0.6,
    "motor_decay_coefficient": 0.1,
    "motor_joint_limit": 0.1,
    "pixels_per_unit": 100,
    "num_shape_roles": 4,
}
"""Kinetix env_params without an equivalent in our engine, with Kinetix's default values (written on export)."""

ENV_PARAM_ORDER = (
    "dt",
    "slop",
    "baumgarte_coefficient_joints_v",
    "baumgarte_coefficient_joints_p",
    "baumgarte_coefficient_fjoint_av",
    "baumgarte_coefficient_rjoint_limit_av",
    "baumgarte_coefficient_collision",
    "joint_stiffness",
    "clip_position",
    "clip_velocity",
    "clip_angular_velocity",
    "base_motor_speed",
    "base_motor_power",
    "base_thruster_power",
    "motor_decay_coefficient",
    "motor_joint_limit",
    "base_friction",
    "max_timesteps",
    "pixels_per_unit",
    "dense_reward_scale",
    "num_shape_roles",
)
"""Kinetix `EnvParams` fields in declaration order."""

KINETIX_UNMODELLED_STATIC: dict[str, object] = {
    "max_polygon_vertices": MAX_VERTICES,
    "num_solver_iterations": 10,
    "solver_batch_size": 16,
    "do_warm_starting": True,
    "num_static_fixated_polys": NUM_BOUNDARY_POLYGONS,
    "screen_dim": {"0": 500, "1": 500},
    "downscale": 4,
    "max_shape_size": 2,
    "num_motor_bindings": 4,
    "num_thruster_bindings": 2,
}
"""Kinetix static_env_params without an equivalent in our static params, with Kinetix's values (written on export)."""

STATIC_ORDER = (
    "num_polygons",
    "num_circles",
    "num_joints",
    "num_thrusters",
    "max_polygon_vertices",
    "num_solver_iterations",
    "solver_batch_size",
    "do_warm_starting",
    "num_static_fixated_polys",
    "screen_dim",
    "downscale",
    "frame_skip",
    "max_shape_size",
    "num_motor_bindings",
    "num_thruster_bindings",
)
"""Kinetix `StaticEnvParams` fields in declaration order."""

KINETIX_MAX_TIMESTEPS = 256
"""Kinetix's loader forces every level's episode length to this many env steps."""


BODY_FIELDS = (
    "position",
    "rotation",
    "velocity",
    "angular_velocity",
    "inverse_mass",
    "inverse_inertia",
    "friction",
    "restitution",
    "collision_mode",
    "active",
    "n_vertices",
    "vertices",
    "radius",
)
"""Jax2D `RigidBody` fields; our `Bodies` fields of the same names have the same meaning and unit (vertex order and
the per-kind fields differ, see above)."""

JOINT_FIELDS: dict[str, str] = {
    "a_index": "body_a",
    "b_index": "body_b",
    "a_relative_pos": "anchor_a",
    "b_relative_pos": "anchor_b",
    "active": "active",
    "motor_speed": "motor_speed",
    "motor_power": "motor_power",
    "motor_on": "motor_on",
    "motor_has_joint_limits": "has_limits",
    "min_rotation": "lower_angle",
    "max_rotation": "upper_angle",
    "is_fixed_joint": "is_fixed",
    "rotation": "reference_angle",
}
"""Jax2D `Joint` field -> our `Joints` field with the same meaning (`global_position`, `acc_impulse` and
`acc_r_impulse` have none)."""

THRUSTER_FIELDS: dict[str, str] = {
    "object_index": "body",
    "relative_position": "anchor",
    "rotation": "angle",
    "power": "power",
    "active": "active",
}
"""Jax2D `Thruster` field -> our `Thrusters` field with the same meaning (`global_position` has none)."""


@dataclasses.dataclass(frozen=True)
class KinetixLevel:
    """A Kinetix level (or a batch of levels) decoded into numpy arrays, named as in Kinetix; one array per field.

    `polygon` / `circle` hold the 13 Jax2D `RigidBody` fields plus `role`, `density` and `highlighted`; `joint` the
    16 `Joint` fields plus `motor_binding`; `thruster` the 6 `Thruster` fields plus `thruster_binding`. Slots are on
    the axis after any leading batch axes (axis 0 for one level).
    """

    polygon: dict[str, np.ndarray]
    circle: dict[str, np.ndarray]
    joint: dict[str, np.ndarray]
    thruster: dict[str, np.ndarray]
    collision_matrix: np.ndarray  # (..., N, N) bool
    gravity: np.ndarray  # (..., 2) [m/s^2]
    env_params: dict[str, float]  # numeric Kinetix env_params (SIM_PARAM_FIELDS, dense_reward_scale); {} if unknown
    static_env_params: dict[str, int]  # num_polygons, num_circles, num_joints, num_thrusters, frame_skip


def reverse_vertex_order(vertices: np.ndarray, n_vertices: np.ndarray) -> np.ndarray:
    """Reverse the first n_vertices points of each (4, 2) block, any leading axes (clockwise <-> counter-clockwise;
    an involution)."""
    count = np.clip(np.asarray(n_vertices), 0, MAX_VERTICES)[..., None]
    point = np.arange(MAX_VERTICES)
    order = np.where(point < count, count - 1 - point, point)
    return np.take_along_axis(np.asarray(vertices), order[..., None], axis=-2)


def static_from_kinetix(kinetix: KinetixLevel) -> StaticEnvParams:
    """Our static params for the level's slot counts and frame skip, with Kinetix's 256-step episodes."""
    return static_from_counts(kinetix.static_env_params)


def static_from_counts(counts: dict[str, int]) -> StaticEnvParams:
    """Our static params for Kinetix slot counts and frame skip (`KinetixLevel.static_env_params` keys), with
    Kinetix's boundary polygons and 256-step episodes."""
    sim = StaticSimParams(
        num_polygons=counts["num_polygons"],
        num_circles=counts["num_circles"],
        num_joints=counts["num_joints"],
        num_thrusters=counts["num_thrusters"],
        num_reserved_static=NUM_BOUNDARY_POLYGONS,
    )
    return StaticEnvParams(sim=sim, frame_skip=counts["frame_skip"], max_timesteps=KINETIX_MAX_TIMESTEPS)


def params_from_kinetix(kinetix: KinetixLevel) -> EnvParams:
    """Our env params: the Kinetix sim parameters we model and the dense reward scale; other fields keep defaults."""
    sim = SimParams(**{ours: float(kinetix.env_params[theirs]) for theirs, ours in SIM_PARAM_FIELDS.items()})
    return EnvParams(sim=sim, dense_reward_scale=float(kinetix.env_params["dense_reward_scale"]))


def _cast_like(template, values: dict[str, np.ndarray]) -> dict[str, jnp.ndarray]:
    """`values` as device arrays of the dtypes of `template`'s fields of the same names."""
    return {name: jnp.asarray(value, getattr(template, name).dtype) for name, value in values.items()}


@functools.partial(jax.jit, static_argnames=("num_bodies", "batch_ndim"))
def _collision_matrix(joints, num_bodies: int, batch_ndim: int) -> jnp.ndarray:
    """`joint_collision_matrix` over `batch_ndim` leading axes, compiled once per size (not op by op)."""
    matrix = functools.partial(joint_collision_matrix, num_bodies=num_bodies)
    for _ in range(batch_ndim):
        matrix = jax.vmap(matrix)
    return matrix(joints)


def level_from_kinetix(kinetix: KinetixLevel, static: StaticEnvParams) -> Level:
    """The `Level` of a decoded Kinetix level, or the batch of levels of a batch (same leading axes): empty contact
    cache, zero joint impulses, no auto motors, collision matrix recomputed from the joints."""
    poly, circ, joint, thr = kinetix.polygon, kinetix.circle, kinetix.joint, kinetix.thruster
    batch = np.shape(poly["active"])[:-1]
    slot_axis = len(batch)

    def both(name):
        return np.concatenate([poly[name], circ[name]], axis=slot_axis)

    circle_slots, polygon_slots = np.shape(circ["active"]), np.shape(poly["active"])
    empty = jax.tree.map(lambda leaf: jnp.asarray(np.broadcast_to(leaf, batch + leaf.shape)), empty_state(static.sim))
    body_values = {name: both(name) for name in BODY_FIELDS} | {
        "vertices": np.concatenate(
            [reverse_vertex_order(poly["vertices"], poly["n_vertices"]), np.zeros(circle_slots + (MAX_VERTICES, 2))],
            axis=slot_axis,
        ),
        "n_vertices": np.concatenate([poly["n_vertices"], np.zeros(circle_slots, int)], axis=slot_axis),
        "radius": np.concatenate([np.zeros(polygon_slots), circ["radius"]], axis=slot_axis),
    }
    bodies = empty.bodies.replace(**_cast_like(empty.bodies, body_values))
    joints = empty.joints.replace(
        **_cast_like(empty.joints, {ours: joint[theirs] for theirs, ours in JOINT_FIELDS.items()})
    )
    thrusters = empty.thrusters.replace(
        **_cast_like(empty.thrusters, {ours: thr[theirs] for theirs, ours in THRUSTER_FIELDS.items()})
    )
    sim = SimState(
        bodies=bodies,
        joints=joints,
        thrusters=thrusters,
        contacts=empty.contacts,
        collision_matrix=_collision_matrix(joints, num_bodies=static.num_bodies, batch_ndim=len(batch)),
        gravity=jnp.asarray(kinetix.gravity, jnp.float32),
    )
    task = Task(
        roles=jnp.asarray(both("role"), jnp.int32),
        densities=jnp.asarray(both("density"), jnp.float32),
        motor_bindings=jnp.asarray(joint["motor_binding"], jnp.int32),
        thruster_bindings=jnp.asarray(thr["thruster_binding"], jnp.int32),
        motor_auto=jnp.asarray(np.zeros(batch + (static.sim.num_joints,), bool)),
    )
    return Level(sim=sim, task=task)


def _anchor_world_position(bodies, body_index: np.ndarray, anchor: np.ndarray) -> np.ndarray:
    """(..., K, 2) world position of body-frame points (Jax2D's `global_position` caches), any leading axes."""
    index = np.asarray(body_index)
    position = np.take_along_axis(np.asarray(bodies.position, np.float64), index[..., None], axis=-2)
    rotation = np.take_along_axis(np.asarray(bodies.rotation, np.float64), index, axis=-1)
    return position + rotate_host(rotation, np.asarray(anchor, np.float64))


def entities_to_kinetix(level: Level, static: StaticEnvParams) -> dict[str, object]:
    """The `KinetixLevel` fields `polygon`, `circle`, `joint`, `thruster`, `collision_matrix` and `gravity` of a
    level or of a batch of levels (leading axes kept); unmodelled fields get Kinetix's defaults."""
    b, j, t, task = level.sim.bodies, level.sim.joints, level.sim.thrusters, level.task
    slot_axis = np.ndim(b.active) - 1

    def host(x):
        return np.asarray(x)

    def split(x):
        return np.split(host(x), [static.sim.num_polygons], axis=slot_axis)

    fields = {name: getattr(b, name) for name in BODY_FIELDS} | {
        "role": task.roles,
        "density": task.densities,
        "highlighted": np.zeros(np.shape(b.active), bool),
    }
    polygon = {name: split(value)[0] for name, value in fields.items()}
    circle = {name: split(value)[1] for name, value in fields.items()}
    polygon["vertices"] = reverse_vertex_order(polygon["vertices"], polygon["n_vertices"])
    polygon["radius"] = np.zeros_like(polygon["radius"])
    circle["vertices"] = np.zeros_like(circle["vertices"])
    circle["n_vertices"] = np.zeros_like(circle["n_vertices"])
    joint = {theirs: host(getattr(j, ours)) for theirs, ours in JOINT_FIELDS.items()} | {
        "global_position": _anchor_world_position(b, host(j.body_a), j.anchor_a),
        "acc_impulse": np.zeros(np.shape(j.anchor_a)),
        "acc_r_impulse": np.zeros(np.shape(j.reference_angle)),
        "motor_binding": host(task.motor_bindings),
    }
    thruster = {theirs: host(getattr(t, ours)) for theirs, ours in THRUSTER_FIELDS.items()} | {
        "global_position": _anchor_world_position(b, host(t.body), t.anchor),
        "thruster_binding": host(task.thruster_bindings),
    }
    return {
        "polygon": polygon,
        "circle": circle,
        "joint": joint,
        "thruster": thruster,
        "collision_matrix": host(level.sim.collision_matrix),
        "gravity": host(level.sim.gravity),
    }


def level_to_kinetix(level: Level, static: StaticEnvParams, params: EnvParams) -> KinetixLevel:
    """The decoded Kinetix form of a level; unmodelled fields get Kinetix's defaults."""
    env_params = {theirs: float(getattr(params.sim, ours)) for theirs, ours in SIM_PARAM_FIELDS.items()}
    env_params["dense_reward_scale"] = float(params.dense_reward_scale)
    env_params["max_timesteps"] = static.max_timesteps
    counts = {
        "num_polygons": static.sim.num_polygons,
        "num_circles": static.sim.num_circles,
        "num_joints": static.sim.num_joints,
        "num_thrusters": static.sim.num_thrusters,
        "frame_skip": static.frame_skip,
    }
    return KinetixLevel(**entities_to_kinetix(level, static), env_params=env_params, static_env_params=counts)
