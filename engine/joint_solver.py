"""Revolute and fixed joints (soft point constraint, angle limits, motor), solved one joint after another.

Preparation works on one scene. Warm starting and solving are rank-polymorphic: per-scene axes first, any
number of trailing batch axes (see `engine.batch_last`), with body velocities and poses as `Motion` triples of
(N+1, *batch) arrays; bodies are selected with one-hot masks because joint endpoints differ per scene. What
depends only on poses (`JointFrames`) is computed for all joints at once before a sweep; the sweep itself is one of
`engine.sweep.SWEEPS` (looped, its body compiled once however many joints there are, or unrolled).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
from flax import struct

from kforge.engine.geometry import rotate
from kforge.engine.softness import Softness
from kforge.engine.state import Joints, StartBodies
from kforge.engine.sweep import Motion, Sweep

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


def prepare_joints(joints: Joints, start: StartBodies, motor_actions, params, substep, motor_rows: bool) -> JointRows:
    """Joint constants from the bodies at the start of the step; `motor_actions` (J,) in [-1, 1]; motors are solved as
    rows only where `motor_rows` (the constraint motor law); `params` (`engine.SimParams`) scales the motors, whose
    impulses are bounded per `substep` [s]."""
    pose, response_scale = start.pose, start.response_scale
    base_motor_speed, base_motor_power = params.base_motor_speed, params.base_motor_power
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
        solve_motor=motor_rows & revolute & joints.motor_on & rotatable & (motor_actions != 0.0),  # 0 = motor off
        solve_limits=revolute & joints.has_limits & rotatable,
        reference_angle=joints.reference_angle,
        lower_angle=joints.lower_angle,
        upper_angle=joints.upper_angle,
        motor_target=joints.motor_speed * base_motor_speed * jnp.clip(motor_actions, -1.0, 1.0),
        motor_max_impulse=joints.motor_power * base_motor_power * axial_mass * substep,
    )


def servo_motor_kick(joints: Joints, start: StartBodies, motor_actions, params) -> jnp.ndarray:
    """(N+1,) change of angular velocity [rad/s] that the servo motor law (`engine.params.MotorLaw.SERVO`) applies
    once per step, before the solve, to the bodies `start` at the start of the step.

    Each motorised revolute joint gives its two bodies opposite angular impulses of
    base_motor_power x motor_power x dt x axial inertia x tanh(motor_decay x speed error), the speed error being the
    joint's relative angular velocity minus its target; near an angle limit the impulse fades linearly to zero over
    `motor_limit_fade` while it drives the joint further towards the limit.
    """
    velocity, pose, response_scale, bodies_active = start.velocity, start.pose, start.response_scale, start.active
    a, b = joints.body_a, joints.body_b
    action = jnp.clip(motor_actions, -1.0, 1.0)
    inverse_inertia_a, inverse_inertia_b = response_scale[a, 2], response_scale[b, 2]
    inverse_sum = inverse_inertia_a + inverse_inertia_b
    axial_mass = 1.0 / jnp.where(inverse_sum > 0, inverse_sum, 1.0)
    bound = params.base_motor_power * joints.motor_power * params.dt * axial_mass
    error = velocity[b, 2] - velocity[a, 2] - joints.motor_speed * action * params.base_motor_speed
    direction = jnp.tanh(error * params.motor_decay)
    angle = pose[b, 2] - pose[a, 2] - joints.reference_angle
    fade = params.motor_limit_fade
    beyond = angle - jnp.clip(angle, joints.lower_angle + fade, joints.upper_angle - fade)
    fading = jnp.where((beyond == 0) | ~joints.has_limits, 1.0, jnp.maximum(0.0, 1.0 - jnp.abs(beyond) / fade))
    fading = jnp.maximum(fading, (jnp.sign(beyond) != jnp.sign(action)).astype(fading.dtype))
    movable = (response_scale[a, 0] + response_scale[b, 0]) > 0
    applies = (
        joints.active
        & ~joints.is_fixed
        & joints.motor_on
        & (action != 0.0)
        & movable
        & bodies_active[a]
        & bodies_active[b]
    )
    impulse = jnp.where(applies, bound * direction * fading, 0.0)
    # Each body sums its joints' impulses in a fixed order (bodies a, then bodies b), the same bits on every
    # backend: a scatter-add onto a body with several joints becomes atomic additions of varying order on a GPU.
    owners = jnp.concatenate([a, b])
    changes = jnp.concatenate([impulse * inverse_inertia_a, -impulse * inverse_inertia_b])
    body = jnp.arange(velocity.shape[0])
    kick = jnp.zeros(velocity.shape[0], velocity.dtype)
    for k in range(owners.shape[0]):
        kick = jnp.where(body == owners[k], kick + changes[k], kick)
    return kick


def _select(component, mask):
    """Rows of a (N+1, *batch) `component` chosen by a (J, N+1, *batch) one-hot mask: (J, *batch)."""
    selected = jnp.zeros(mask[:, 0].shape, component.dtype)
    for row in range(component.shape[0]):
        selected = jnp.where(mask[:, row], component[row][None], selected)
    return selected


@struct.dataclass
class JointFrames:
    """Pose-dependent joint data of one solver pass, for every joint at once: (J, *batch) arrays or tuples of them.

    Poses do not change during a pass, so this is computed before the sequential sweep, vectorised over joints;
    the sweep itself only carries velocities.
    """

    mask_a: jnp.ndarray  # (J, N+1, *batch) bool one-hot of body a
    mask_b: jnp.ndarray
    lever_a: tuple  # x, y [m] anchor offset from a's centre, turned by a's rotation since the step start
    lever_b: tuple
    angle: jnp.ndarray  # [rad] rotation_b - rotation_a - reference angle
    gap: tuple  # x, y [m] anchor of b minus anchor of a
    point_matrix: tuple  # k11, k12, k22 [1/kg] effective inverse mass matrix of the point constraint
    inverse_determinant: jnp.ndarray  # [kg^2] 1 / det of that matrix, 0 where the point constraint is not solved


def joint_frames(rows: JointRows, pose: Motion, start_rotation) -> JointFrames:
    """Frames of every joint at poses `pose`; `start_rotation` (N+1, *batch) [rad] is the rotation at step start."""
    index = jnp.arange(start_rotation.shape[0]).reshape((1, -1) + (1,) * (rows.body_a.ndim - 1))
    mask_a, mask_b = index == rows.body_a[:, None], index == rows.body_b[:, None]
    pose_a = tuple(_select(component, mask_a) for component in pose)
    pose_b = tuple(_select(component, mask_b) for component in pose)

    def turned(lever, rotation, mask):
        angle = rotation - _select(start_rotation, mask)
        c, s = jnp.cos(angle), jnp.sin(angle)
        return c * lever[:, 0] - s * lever[:, 1], s * lever[:, 0] + c * lever[:, 1]

    (ax, ay), (bx, by) = turned(rows.lever_a, pose_a[2], mask_a), turned(rows.lever_b, pose_b[2], mask_b)
    ia, ib = rows.response_a[:, 2], rows.response_b[:, 2]
    ma, mb = rows.response_a[:, 0], rows.response_b[:, 0]
    k11 = ma + mb + ay**2 * ia + by**2 * ib
    k12 = -ay * ax * ia - by * bx * ib
    k22 = ma + mb + ax**2 * ia + bx**2 * ib
    det = k11 * k22 - k12 * k12
    solvable = rows.solve_point & (det > SINGULAR_DETERMINANT)
    return JointFrames(
        mask_a=mask_a,
        mask_b=mask_b,
        lever_a=(ax, ay),
        lever_b=(bx, by),
        angle=pose_b[2] - pose_a[2] - rows.reference_angle,
        gap=((pose_b[0] + bx) - (pose_a[0] + ax), (pose_b[1] + by) - (pose_a[1] + ay)),
        point_matrix=(k11, k12, k22),
        inverse_determinant=jnp.where(solvable, 1.0 / jnp.where(solvable, det, 1.0), 0.0),
    )


def _take(tree, j):
    return jax.tree_util.tree_map(lambda x: x[j], tree)


def _select_motion(motion: Motion, mask) -> Motion:
    """Components of the body chosen by a (N+1, *batch) one-hot mask."""
    return tuple(_select(component, mask[None])[0] for component in motion)


def _apply_impulse(velocity: Motion, row: JointRows, frame: JointFrames, linear, axial) -> Motion:
    """Velocities after one joint's linear impulse `linear` (x, y) at the anchors and angular impulse `axial`.

    The velocity changes depend only on the impulse and the frame, so they are added to the two bodies' rows by
    their masks without reading the old velocities first.
    """
    (ax, ay), (bx, by) = frame.lever_a, frame.lever_b
    turn_a = ax * linear[1] - ay * linear[0] + axial
    turn_b = bx * linear[1] - by * linear[0] + axial
    ra, rb = row.response_a, row.response_b
    change_a = (-ra[0] * linear[0], -ra[1] * linear[1], -ra[2] * turn_a)
    change_b = (rb[0] * linear[0], rb[1] * linear[1], rb[2] * turn_b)
    return tuple(
        v + jnp.where(frame.mask_a, da[None], 0.0) + jnp.where(frame.mask_b, db[None], 0.0)
        for v, da, db in zip(velocity, change_a, change_b, strict=True)
    )


def _axial(impulse: JointImpulses):
    """Net angular impulse on b (and, negated, on a) of one joint's angular rows."""
    return impulse.angular + impulse.motor + impulse.limit[0] - impulse.limit[1]


def warm_start_joints(velocity: Motion, rows: JointRows, frames: JointFrames, impulses: JointImpulses) -> Motion:
    """Apply every joint's accumulated impulses to the velocities, one joint after another.

    Nothing is solved, so the joints are unrolled: XLA fuses the chain of updates into one loop per component.
    """
    for j in range(rows.body_a.shape[0]):
        impulse = _take(impulses, j)
        velocity = _apply_impulse(velocity, _take(rows, j), _take(frames, j), impulse.linear, _axial(impulse))
    return velocity


@dataclasses.dataclass(frozen=True)
class JointPass:
    """How one sweep over the joints solves: the soft rows' settings, the laws (static) and the sweep's form."""

    softness: Softness
    inverse_substep: jnp.ndarray  # [1/s]
    use_bias: bool | jnp.ndarray  # the soft position-correcting solve, otherwise the relaxing solve (may be traced)
    constraint_motors: bool  # static: motors are rows (`engine.params.MotorLaw.CONSTRAINT`)
    sweep: Sweep  # one of `engine.sweep.SWEEPS`


def _angular_row(axial_mass, relative_speed, error, old, settings: JointPass, one_sided: bool):
    """New impulse of an angular row driving `relative_speed` and the position `error` to zero.

    One-sided rows (limits) are speculative while `error` > 0: they only stop the motion that would cross it; past it
    (`error` < 0) they turn back as fast as the joint's softness.
    """
    softness, use_bias = settings.softness, settings.use_bias
    bias = jnp.where(use_bias, softness.bias_rate * error, 0.0)
    mass_scale = jnp.where(use_bias, softness.mass_scale, 1.0)
    impulse_scale = jnp.where(use_bias, softness.impulse_scale, 0.0)
    if one_sided:
        ahead = error > 0
        bias = jnp.where(ahead, error * settings.inverse_substep, bias)
        mass_scale = jnp.where(ahead, 1.0, mass_scale)
        impulse_scale = jnp.where(ahead, 0.0, impulse_scale)
    return old - axial_mass * mass_scale * (relative_speed + bias) - impulse_scale * old


def _motor_row(row: JointRows, impulse: JointImpulses, wa, wb, settings: JointPass):
    """The motor's velocity row with a bounded impulse (the servo law acted before the solve): new motor impulse and
    the two angular velocities after it."""
    new_motor = impulse.motor
    if settings.constraint_motors:
        ia, ib = row.response_a[2], row.response_b[2]
        bound = row.motor_max_impulse
        new_motor = jnp.clip(impulse.motor - row.axial_mass * (wb - wa - row.motor_target), -bound, bound)
        new_motor = jnp.where(row.solve_motor, new_motor, 0.0)
        wa, wb = wa - ia * (new_motor - impulse.motor), wb + ib * (new_motor - impulse.motor)
    return new_motor, wa, wb


def _limit_rows(row: JointRows, frame: JointFrames, impulse: JointImpulses, wa, wb, settings: JointPass):
    """The angle limits as one-sided speculative rows: the new lower and upper limit impulses and the two angular
    velocities after them."""
    ia, ib = row.response_a[2], row.response_b[2]
    mass = row.axial_mass
    lower_old, upper_old = impulse.limit[0], impulse.limit[1]
    lower = _angular_row(mass, wb - wa, frame.angle - row.lower_angle, lower_old, settings, True)
    lower = jnp.where(row.solve_limits, jnp.maximum(lower, 0.0), 0.0)
    lower_change = lower - lower_old
    upper_speed = (wa - ia * lower_change) - (wb + ib * lower_change)
    upper = _angular_row(mass, upper_speed, row.upper_angle - frame.angle, upper_old, settings, True)
    upper = jnp.where(row.solve_limits, jnp.maximum(upper, 0.0), 0.0)
    wa, wb = wa - ia * (lower - lower_old), wb + ib * (lower - lower_old)
    wa, wb = wa - ia * (upper_old - upper), wb + ib * (upper_old - upper)
    return (lower, upper), wa, wb


def _point_row(frame: JointFrames, old_linear, velocities: tuple[Motion, Motion], wa, wb, settings: JointPass):
    """The point constraint, anchors coinciding (a 2x2 effective-mass solve): the new linear impulse (x, y);
    `velocities` holds the motions of bodies a and b, `wa` and `wb` their angular velocities after the angular rows."""
    vel_a, vel_b = velocities
    softness, use_bias = settings.softness, settings.use_bias
    (ax, ay), (bx, by) = frame.lever_a, frame.lever_b
    bias_rate = jnp.where(use_bias, softness.bias_rate, 0.0)
    target_x = (vel_b[0] - wb * by) - (vel_a[0] - wa * ay) + bias_rate * frame.gap[0]
    target_y = (vel_b[1] + wb * bx) - (vel_a[1] + wa * ax) + bias_rate * frame.gap[1]
    k11, k12, k22 = frame.point_matrix
    solved_x = frame.inverse_determinant * (k22 * target_x - k12 * target_y)
    solved_y = frame.inverse_determinant * (k11 * target_y - k12 * target_x)
    mass_scale = jnp.where(use_bias, softness.mass_scale, 1.0)
    impulse_scale = jnp.where(use_bias, softness.impulse_scale, 0.0)
    solvable = frame.inverse_determinant != 0.0
    return tuple(
        jnp.where(solvable, old - mass_scale * change - impulse_scale * old, 0.0)
        for old, change in ((old_linear[0], solved_x), (old_linear[1], solved_y))
    )


def _solve_joint(
    row: JointRows, frame: JointFrames, impulse: JointImpulses, velocities: tuple[Motion, Motion], settings: JointPass
) -> JointImpulses:
    """New impulses of one joint, its rows solved in order (motor, limits, fixed angle, point), each seeing the velocity
    changes of the ones before; `velocities` holds the motions of its bodies a and b."""
    vel_a, vel_b = velocities
    ia, ib = row.response_a[2], row.response_b[2]
    new_motor, wa, wb = _motor_row(row, impulse, vel_a[2], vel_b[2], settings)
    limit, wa, wb = _limit_rows(row, frame, impulse, wa, wb, settings)
    # Fixed joint: relative angle held at the reference.
    new_angular = _angular_row(row.axial_mass, wb - wa, frame.angle, impulse.angular, settings, False)
    new_angular = jnp.where(row.solve_angle, new_angular, 0.0)
    wa, wb = wa - ia * (new_angular - impulse.angular), wb + ib * (new_angular - impulse.angular)
    linear = _point_row(frame, impulse.linear, velocities, wa, wb, settings)
    return JointImpulses(linear=jnp.stack(linear), angular=new_angular, motor=new_motor, limit=jnp.stack(limit))


def solve_joints(velocity: Motion, rows: JointRows, frames: JointFrames, impulses: JointImpulses, settings: JointPass):
    """One sweep (`settings.sweep`) over the joints in index order: motor, limits, fixed angle, then the point
    constraint. Returns the velocities and the new impulses.
    """

    def gather(velocity, j):
        frame = _take(frames, j)
        return _select_motion(velocity, frame.mask_a), _select_motion(velocity, frame.mask_b)

    def solve(velocities, j, start: JointImpulses):
        return _solve_joint(_take(rows, j), _take(frames, j), start, velocities, settings)

    def apply(velocity, j, change: JointImpulses):
        return _apply_impulse(velocity, _take(rows, j), _take(frames, j), change.linear, _axial(change))

    return settings.sweep(velocity, rows.body_a.shape[0], impulses, gather, solve, apply)
