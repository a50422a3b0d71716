"""Revolute and fixed joints (soft point constraint, angle limits, motor), solved one joint after another.

Preparation works on one scene. Warm starting and solving are rank-polymorphic: per-scene axes first, any
number of trailing batch axes (see `engine.batch_last`); bodies are selected with one-hot masks because joint
endpoints differ per scene.
"""

from __future__ import annotations

import jax.numpy as jnp
from flax import struct

from engine.geometry import rotate
from engine.softness import Softness
from engine.state import Joints

SINGULAR_DETERMINANT = 1e-12
"""Point-constraint matrices with a smaller determinant (both bodies immovable) are not solved."""


@struct.dataclass
class JointRows:
    """Per-joint constants of one step."""

    body_a: jnp.ndarray  # (J,) i32
    body_b: jnp.ndarray  # (J,) i32
    lever_a: jnp.ndarray  # (J, 2) [m] anchor offset from a's centre, world frame, at the start of the step
    lever_b: jnp.ndarray  # (J, 2)
    response_a: jnp.ndarray  # (J, 3) inverse mass, inverse mass, inverse inertia of a
    response_b: jnp.ndarray  # (J, 3)
    axial_mass: jnp.ndarray  # (J,) [kg m^2] 1 / (1/I_a + 1/I_b); 0 if neither can rotate
    solve_point: jnp.ndarray  # (J,) bool: active joint with at least one movable body
    solve_angle: jnp.ndarray  # (J,) bool: fixed joint that can rotate
    solve_motor: jnp.ndarray  # (J,) bool
    solve_limits: jnp.ndarray  # (J,) bool
    reference_angle: jnp.ndarray  # (J,) [rad]
    lower_angle: jnp.ndarray  # (J,) [rad]
    upper_angle: jnp.ndarray  # (J,) [rad]
    motor_target: jnp.ndarray  # (J,) [rad/s] target of angular_velocity_b - angular_velocity_a
    motor_max_impulse: jnp.ndarray  # (J,) [N m s] per substep


@struct.dataclass
class JointImpulses:
    """Accumulated per-substep joint impulses."""

    linear: jnp.ndarray  # (J, 2) [N s]
    angular: jnp.ndarray  # (J,) [N m s]
    motor: jnp.ndarray  # (J,) [N m s]
    limit: jnp.ndarray  # (J, 2) [N m s] lower, upper (both >= 0)


def prepare_joints(
    joints: Joints, pose, response_scale, motor_actions, base_motor_speed, base_motor_power, substep
) -> JointRows:
    """Joint constants from start-of-step poses (N+1, 3); `motor_actions` (J,) in [-1, 1]."""
    a, b = joints.body_a, joints.body_b
    response_a, response_b = response_scale[a], response_scale[b]
    inverse_inertia_sum = response_a[:, 2] + response_b[:, 2]
    axial_mass = jnp.where(
        inverse_inertia_sum > 0, 1.0 / jnp.where(inverse_inertia_sum > 0, inverse_inertia_sum, 1.0), 0.0
    )
    movable = (response_a[:, 0] + response_b[:, 0] + inverse_inertia_sum) > 0
    revolute = joints.active & ~joints.is_fixed & movable
    rotatable = inverse_inertia_sum > 0
    return JointRows(
        body_a=a,
        body_b=b,
        lever_a=rotate(pose[a, 2], joints.anchor_a),
        lever_b=rotate(pose[b, 2], joints.anchor_b),
        response_a=response_a,
        response_b=response_b,
        axial_mass=axial_mass,
        solve_point=joints.active & movable,
        solve_angle=joints.active & joints.is_fixed & rotatable,
        solve_motor=revolute & joints.motor_on & rotatable & (motor_actions != 0.0),  # action 0 = motor off
        solve_limits=revolute & joints.has_limits & rotatable,
        reference_angle=joints.reference_angle,
        lower_angle=joints.lower_angle,
        upper_angle=joints.upper_angle,
        motor_target=joints.motor_speed * base_motor_speed * jnp.clip(motor_actions, -1.0, 1.0),
        motor_max_impulse=joints.motor_power * base_motor_power * axial_mass * substep,
    )


def _rotate_leading(angle, vector):
    """Rotate (2, *batch) vectors by `angle` (*batch) radians."""
    c, s = jnp.cos(angle), jnp.sin(angle)
    return jnp.stack([c * vector[0] - s * vector[1], s * vector[0] + c * vector[1]])


def _cross_leading(a, b):
    return a[0] * b[1] - a[1] * b[0]


def _one_hot(index, num_rows):
    """(num_rows, *batch) bool mask selecting `index` (*batch)."""
    return jnp.arange(num_rows).reshape((-1,) + (1,) * index.ndim) == index[None]


def _select(array, mask):
    """Row of (R, 3, *batch) `array` chosen by a (R, *batch) one-hot mask: (3, *batch)."""
    selected = jnp.zeros_like(array[0])
    for row in range(array.shape[0]):
        selected = jnp.where(mask[row][None], array[row], selected)
    return selected


def _replace(array, mask, row):
    return jnp.where(mask[:, None], row[None], array)


def _joint_frame(rows: JointRows, j, pose, start_pose):
    """One-hot masks of the joint's bodies, their current poses, and the current world levers."""
    mask_a = _one_hot(rows.body_a[j], pose.shape[0])
    mask_b = _one_hot(rows.body_b[j], pose.shape[0])
    pose_a, pose_b = _select(pose, mask_a), _select(pose, mask_b)
    lever_a = _rotate_leading(pose_a[2] - _select(start_pose, mask_a)[2], rows.lever_a[j])
    lever_b = _rotate_leading(pose_b[2] - _select(start_pose, mask_b)[2], rows.lever_b[j])
    return mask_a, mask_b, pose_a, pose_b, lever_a, lever_b


def _push(vel_a, vel_b, rows: JointRows, j, lever_a, lever_b, linear, axial):
    """Velocities after a linear impulse `linear` (2, *batch) at the levers plus an angular impulse `axial`."""
    turn_a = _cross_leading(lever_a, linear) + axial
    turn_b = _cross_leading(lever_b, linear) + axial
    vel_a = vel_a - rows.response_a[j] * jnp.concatenate([linear, turn_a[None]])
    vel_b = vel_b + rows.response_b[j] * jnp.concatenate([linear, turn_b[None]])
    return vel_a, vel_b


def warm_start_joints(velocity, pose, start_pose, rows: JointRows, impulses: JointImpulses):
    """Apply every joint's accumulated impulses to the (N+1, 3, *batch) velocities."""
    for j in range(rows.body_a.shape[0]):
        mask_a, mask_b, _, _, lever_a, lever_b = _joint_frame(rows, j, pose, start_pose)
        axial = impulses.angular[j] + impulses.motor[j] + impulses.limit[j, 0] - impulses.limit[j, 1]
        linear = impulses.linear[j]
        vel_a, vel_b = _push(
            _select(velocity, mask_a), _select(velocity, mask_b), rows, j, lever_a, lever_b, linear, axial
        )
        velocity = _replace(_replace(velocity, mask_a, vel_a), mask_b, vel_b)
    return velocity


def _spin(vel_a, vel_b, ia, ib, delta):
    """Velocities after an angular impulse `delta` turning b positively and a negatively."""
    return vel_a.at[2].add(-ia * delta), vel_b.at[2].add(ib * delta)


def _angular_row(
    axial_mass, relative_speed, error, old, softness: Softness, use_bias, inverse_substep, one_sided: bool
):
    """New impulse of an angular row driving `relative_speed` and the position `error` to zero.

    One-sided rows (limits) are speculative while `error` > 0: they only stop the motion that would cross it.
    """
    bias = jnp.where(use_bias, softness.bias_rate * error, 0.0)
    mass_scale = jnp.where(use_bias, softness.mass_scale, 1.0)
    impulse_scale = jnp.where(use_bias, softness.impulse_scale, 0.0)
    if one_sided:
        ahead = error > 0
        bias = jnp.where(ahead, error * inverse_substep, bias)
        mass_scale = jnp.where(ahead, 1.0, mass_scale)
        impulse_scale = jnp.where(ahead, 0.0, impulse_scale)
    return old - axial_mass * mass_scale * (relative_speed + bias) - impulse_scale * old


def solve_joints(
    velocity, pose, start_pose, rows: JointRows, impulses: JointImpulses, softness: Softness, inverse_substep, use_bias
):
    """One sweep over the joints in index order: motor, limits, fixed angle, then the point constraint."""
    linear, angular, motor, limit = impulses.linear, impulses.angular, impulses.motor, impulses.limit
    for j in range(rows.body_a.shape[0]):
        mask_a, mask_b, pose_a, pose_b, lever_a, lever_b = _joint_frame(rows, j, pose, start_pose)
        vel_a, vel_b = _select(velocity, mask_a), _select(velocity, mask_b)
        ia, ib = rows.response_a[j][2], rows.response_b[j][2]
        mass = rows.axial_mass[j]
        angle = pose_b[2] - pose_a[2] - rows.reference_angle[j]

        # Motor: velocity row with a bounded impulse.
        bound = rows.motor_max_impulse[j]
        new_motor = jnp.clip(motor[j] - mass * (vel_b[2] - vel_a[2] - rows.motor_target[j]), -bound, bound)
        new_motor = jnp.where(rows.solve_motor[j], new_motor, 0.0)
        vel_a, vel_b = _spin(vel_a, vel_b, ia, ib, new_motor - motor[j])
        # Limits: one-sided rows.
        lower = _angular_row(
            mass,
            vel_b[2] - vel_a[2],
            angle - rows.lower_angle[j],
            limit[j, 0],
            softness,
            use_bias,
            inverse_substep,
            True,
        )
        lower = jnp.where(rows.solve_limits[j], jnp.maximum(lower, 0.0), 0.0)
        vel_a, vel_b = _spin(vel_a, vel_b, ia, ib, lower - limit[j, 0])
        upper = _angular_row(
            mass,
            vel_a[2] - vel_b[2],
            rows.upper_angle[j] - angle,
            limit[j, 1],
            softness,
            use_bias,
            inverse_substep,
            True,
        )
        upper = jnp.where(rows.solve_limits[j], jnp.maximum(upper, 0.0), 0.0)
        vel_a, vel_b = _spin(vel_a, vel_b, ia, ib, limit[j, 1] - upper)
        # Fixed joint: relative angle held at the reference.
        new_angular = _angular_row(
            mass, vel_b[2] - vel_a[2], angle, angular[j], softness, use_bias, inverse_substep, False
        )
        new_angular = jnp.where(rows.solve_angle[j], new_angular, 0.0)
        vel_a, vel_b = _spin(vel_a, vel_b, ia, ib, new_angular - angular[j])
        # Point constraint: anchors coincide (2x2 effective-mass solve).
        point_a = vel_a[:2] + vel_a[2] * jnp.stack([-lever_a[1], lever_a[0]])
        point_b = vel_b[:2] + vel_b[2] * jnp.stack([-lever_b[1], lever_b[0]])
        relative = point_b - point_a
        ma, mb = rows.response_a[j][0], rows.response_b[j][0]
        k11 = ma + mb + lever_a[1] ** 2 * ia + lever_b[1] ** 2 * ib
        k12 = -lever_a[1] * lever_a[0] * ia - lever_b[1] * lever_b[0] * ib
        k22 = ma + mb + lever_a[0] ** 2 * ia + lever_b[0] ** 2 * ib
        det = k11 * k22 - k12 * k12
        solvable = rows.solve_point[j] & (det > SINGULAR_DETERMINANT)
        inverse_det = jnp.where(solvable, 1.0 / jnp.where(solvable, det, 1.0), 0.0)
        gap = (pose_b[:2] + lever_b) - (pose_a[:2] + lever_a)
        target = relative + jnp.where(use_bias, softness.bias_rate, 0.0) * gap
        mass_scale = jnp.where(use_bias, softness.mass_scale, 1.0)
        impulse_scale = jnp.where(use_bias, softness.impulse_scale, 0.0)
        solved = inverse_det * jnp.stack([k22 * target[0] - k12 * target[1], k11 * target[1] - k12 * target[0]])
        new_linear = jnp.where(solvable, linear[j] - mass_scale * solved - impulse_scale * linear[j], 0.0)
        vel_a, vel_b = _push(vel_a, vel_b, rows, j, lever_a, lever_b, new_linear - linear[j], 0.0)
        velocity = _replace(_replace(velocity, mask_a, vel_a), mask_b, vel_b)
        linear = linear.at[j].set(new_linear)
        angular = angular.at[j].set(new_angular)
        motor = motor.at[j].set(new_motor)
        limit = limit.at[j].set(jnp.stack([lower, upper]))
    return velocity, JointImpulses(linear, angular, motor, limit)
