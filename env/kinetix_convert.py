"""Field mapping between a decoded Kinetix level (Jax2D field names, per-kind numpy arrays) and our env types.

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

import jax.numpy as jnp
import numpy as np

from engine import SimParams, SimState, StaticSimParams, empty_state
from engine.collision_filter import joint_collision_matrix
from engine.geometry import rotate_host
from env.params import EnvParams, StaticEnvParams
from env.state import Level, Task

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


@dataclasses.dataclass(frozen=True)
class KinetixLevel:
    """A Kinetix level decoded into numpy arrays, named as in Kinetix; one array per field, slots on axis 0.

    `polygon` / `circle` hold the 13 Jax2D `RigidBody` fields plus `role`, `density` and `highlighted`; `joint` the
    16 `Joint` fields plus `motor_binding`; `thruster` the 6 `Thruster` fields plus `thruster_binding`.
    """

    polygon: dict[str, np.ndarray]
    circle: dict[str, np.ndarray]
    joint: dict[str, np.ndarray]
    thruster: dict[str, np.ndarray]
    collision_matrix: np.ndarray  # (N, N) bool
    gravity: np.ndarray  # (2,) [m/s^2]
    env_params: dict[str, float]  # numeric Kinetix env_params, at least SIM_PARAM_FIELDS and dense_reward_scale
    static_env_params: dict[str, int]  # num_polygons, num_circles, num_joints, num_thrusters, frame_skip


def _kinetix_order_to_ours(vertices: np.ndarray, n_vertices: np.ndarray) -> np.ndarray:
    """Reverse the first n_vertices points of each (4, 2) block (clockwise <-> counter-clockwise; an involution)."""
    out = vertices.copy()
    for slot, n in enumerate(n_vertices):
        out[slot, :n] = vertices[slot, :n][::-1]
    return out


def static_from_kinetix(kinetix: KinetixLevel) -> StaticEnvParams:
    """Our static params for the level's slot counts and frame skip, with Kinetix's 256-step episodes."""
    counts = kinetix.static_env_params
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


def level_from_kinetix(kinetix: KinetixLevel, static: StaticEnvParams) -> Level:
    """The `Level` of a decoded Kinetix level: empty contact cache, collision matrix recomputed from the joints."""
    poly, circ, joint, thr = kinetix.polygon, kinetix.circle, kinetix.joint, kinetix.thruster

    def both(name):
        return np.concatenate([poly[name], circ[name]])

    num_circles = len(circ["active"])
    vertices = np.concatenate(
        [_kinetix_order_to_ours(poly["vertices"], poly["n_vertices"]), np.zeros((num_circles, MAX_VERTICES, 2))]
    )
    empty = empty_state(static.sim)
    f32 = jnp.float32
    bodies = empty.bodies.replace(
        position=jnp.asarray(both("position"), f32),
        rotation=jnp.asarray(both("rotation"), f32),
        velocity=jnp.asarray(both("velocity"), f32),
        angular_velocity=jnp.asarray(both("angular_velocity"), f32),
        inverse_mass=jnp.asarray(both("inverse_mass"), f32),
        inverse_inertia=jnp.asarray(both("inverse_inertia"), f32),
        friction=jnp.asarray(both("friction"), f32),
        restitution=jnp.asarray(both("restitution"), f32),
        collision_mode=jnp.asarray(both("collision_mode"), jnp.int32),
        active=jnp.asarray(both("active"), bool),
        n_vertices=jnp.asarray(np.concatenate([poly["n_vertices"], np.zeros(num_circles, int)]), jnp.int32),
        vertices=jnp.asarray(vertices, f32),
        radius=jnp.asarray(np.concatenate([np.zeros(len(poly["active"])), circ["radius"]]), f32),
    )
    joints = empty.joints.replace(
        body_a=jnp.asarray(joint["a_index"], jnp.int32),
        body_b=jnp.asarray(joint["b_index"], jnp.int32),
        anchor_a=jnp.asarray(joint["a_relative_pos"], f32),
        anchor_b=jnp.asarray(joint["b_relative_pos"], f32),
        reference_angle=jnp.asarray(joint["rotation"], f32),
        active=jnp.asarray(joint["active"], bool),
        is_fixed=jnp.asarray(joint["is_fixed_joint"], bool),
        motor_on=jnp.asarray(joint["motor_on"], bool),
        motor_speed=jnp.asarray(joint["motor_speed"], f32),
        motor_power=jnp.asarray(joint["motor_power"], f32),
        has_limits=jnp.asarray(joint["motor_has_joint_limits"], bool),
        lower_angle=jnp.asarray(joint["min_rotation"], f32),
        upper_angle=jnp.asarray(joint["max_rotation"], f32),
    )
    thrusters = empty.thrusters.replace(
        body=jnp.asarray(thr["object_index"], jnp.int32),
        anchor=jnp.asarray(thr["relative_position"], f32),
        angle=jnp.asarray(thr["rotation"], f32),
        power=jnp.asarray(thr["power"], f32),
        active=jnp.asarray(thr["active"], bool),
    )
    sim = SimState(
        bodies=bodies,
        joints=joints,
        thrusters=thrusters,
        contacts=empty.contacts,
        collision_matrix=joint_collision_matrix(joints, static.num_bodies),
        gravity=jnp.asarray(kinetix.gravity, f32),
    )
    task = Task(
        roles=jnp.asarray(both("role"), jnp.int32),
        densities=jnp.asarray(both("density"), f32),
        motor_bindings=jnp.asarray(joint["motor_binding"], jnp.int32),
        thruster_bindings=jnp.asarray(thr["thruster_binding"], jnp.int32),
        motor_auto=jnp.zeros(static.sim.num_joints, bool),
    )
    return Level(sim=sim, task=task)


def _anchor_world_position(bodies, body_index: np.ndarray, anchor: np.ndarray) -> np.ndarray:
    """(K, 2) world position of body-frame points (Jax2D's `global_position` caches)."""
    position = np.asarray(bodies.position, np.float64)[body_index]
    rotation = np.asarray(bodies.rotation, np.float64)[body_index]
    return position + rotate_host(rotation, np.asarray(anchor, np.float64))


def level_to_kinetix(level: Level, static: StaticEnvParams, params: EnvParams) -> KinetixLevel:
    """The decoded Kinetix form of a level; unmodelled fields get Kinetix's defaults."""
    b, j, t, task = level.sim.bodies, level.sim.joints, level.sim.thrusters, level.task
    p = static.sim.num_polygons

    def host(x):
        return np.asarray(x)

    def split(x):
        x = host(x)
        return x[:p], x[p:]

    fields = {
        "position": b.position,
        "rotation": b.rotation,
        "velocity": b.velocity,
        "angular_velocity": b.angular_velocity,
        "inverse_mass": b.inverse_mass,
        "inverse_inertia": b.inverse_inertia,
        "friction": b.friction,
        "restitution": b.restitution,
        "collision_mode": b.collision_mode,
        "active": b.active,
        "n_vertices": b.n_vertices,
        "vertices": b.vertices,
        "radius": b.radius,
        "role": task.roles,
        "density": task.densities,
        "highlighted": np.zeros(static.num_bodies, bool),
    }
    polygon = {name: split(value)[0] for name, value in fields.items()}
    circle = {name: split(value)[1] for name, value in fields.items()}
    polygon["vertices"] = _kinetix_order_to_ours(polygon["vertices"], polygon["n_vertices"])
    polygon["radius"] = np.zeros_like(polygon["radius"])
    circle["vertices"] = np.zeros_like(circle["vertices"])
    circle["n_vertices"] = np.zeros_like(circle["n_vertices"])
    joint = {
        "a_index": host(j.body_a),
        "b_index": host(j.body_b),
        "a_relative_pos": host(j.anchor_a),
        "b_relative_pos": host(j.anchor_b),
        "global_position": _anchor_world_position(b, host(j.body_a), j.anchor_a),
        "active": host(j.active),
        "acc_impulse": np.zeros((static.sim.num_joints, 2)),
        "acc_r_impulse": np.zeros(static.sim.num_joints),
        "motor_speed": host(j.motor_speed),
        "motor_power": host(j.motor_power),
        "motor_on": host(j.motor_on),
        "motor_has_joint_limits": host(j.has_limits),
        "min_rotation": host(j.lower_angle),
        "max_rotation": host(j.upper_angle),
        "is_fixed_joint": host(j.is_fixed),
        "rotation": host(j.reference_angle),
        "motor_binding": host(task.motor_bindings),
    }
    thruster = {
        "object_index": host(t.body),
        "relative_position": host(t.anchor),
        "rotation": host(t.angle),
        "power": host(t.power),
        "global_position": _anchor_world_position(b, host(t.body), t.anchor),
        "active": host(t.active),
        "thruster_binding": host(task.thruster_bindings),
    }
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
    return KinetixLevel(
        polygon=polygon,
        circle=circle,
        joint=joint,
        thruster=thruster,
        collision_matrix=host(level.sim.collision_matrix),
        gravity=host(level.sim.gravity),
        env_params=env_params,
        static_env_params=counts,
    )
