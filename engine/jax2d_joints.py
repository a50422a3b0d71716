"""Jax2D's joint law (`engine.params.JointLaw.JAX2D`): each pass, joint after joint, an under-relaxed impulse along
the anchors' relative velocity plus a velocity bias from their gap, and a direct move of both bodies' positions
towards each other; fixed joints and joints beyond a limit get an angular impulse. Rank-polymorphic like
`engine.joint_solver`: `Motion` triples of (N+1, *batch) arrays, bodies selected by the frames' one-hot masks.

The impulses stored in `JointImpulses` keep the soft law's convention (the impulse on body b); the linear one is the
sum of every pass's impulse since the scene started, which warm starts the next step (`warm_start_joints`)."""

from __future__ import annotations

import jax.numpy as jnp

from kforge.engine.joint_solver import JointFrames, JointImpulses, JointRows, _select_motion, _take

GAP_VELOCITY_RATE = 2.0
"""[1/s] Velocity bias per metre of gap between a joint's anchors (Jax2D's `baumgarte_coefficient_joints_v`)."""
GAP_POSITION_SHARE = 0.7
"""[-] Share of the anchors' gap closed by moving the bodies each pass (Jax2D's `baumgarte_coefficient_joints_p`)."""
IMPULSE_SHARE = 0.6
"""[-] Share of the computed point impulse applied in a pass (Jax2D's `joint_stiffness`)."""
FIXED_ANGLE_RATE = 2.0
"""[1/s] Angular velocity bias per radian a fixed joint is turned from its reference (Jax2D's
`baumgarte_coefficient_fjoint_av`)."""
LIMIT_ANGLE_RATE = 5.0
"""[1/s] Angular velocity bias per radian a joint is beyond a limit (`baumgarte_coefficient_rjoint_limit_av`)."""


def _one_or(x):
    """x, with 1 where it is 0 (Jax2D's guard against dividing by zero)."""
    return jnp.where(x == 0.0, 1.0, x)


def _cross(a, b):
    return a[0] * b[1] - a[1] * b[0]


def _meeting_point(anchor_a, anchor_b, ma, mb):
    """Where Jax2D's joint acts: the anchors' average weighted by the bodies' masses (a static body's anchor)."""
    weight_a, weight_b = _one_or(ma), _one_or(mb)
    return tuple(
        jnp.where(
            ma == 0.0,
            anchor_a[k],
            jnp.where(
                mb == 0.0,
                anchor_b[k],
                (anchor_a[k] / weight_a + anchor_b[k] / weight_b) / (1.0 / weight_a + 1.0 / weight_b),
            ),
        )
        for k in range(2)
    )


def _point_impulse(row: JointRows, frame: JointFrames, moving_a, moving_b, gap):
    """The under-relaxed impulse on body a along the anchors' relative velocity at their meeting point, biased by
    their `gap`; `moving_a` and `moving_b` hold each body's position and velocity."""
    (position_a, velocity_a), (position_b, velocity_b) = moving_a, moving_b
    ma, ia = row.response_a[0], row.response_a[2]
    mb, ib = row.response_b[0], row.response_b[2]
    lever_a, lever_b = frame.lever_a, frame.lever_b
    anchor_a = tuple(position_a[k] + lever_a[k] for k in range(2))
    anchor_b = tuple(position_b[k] + lever_b[k] for k in range(2))
    point = _meeting_point(anchor_a, anchor_b, ma, mb)

    def point_velocity(motion, position):
        arm = (point[0] - position[0], point[1] - position[1])
        return motion[0] - motion[2] * arm[1], motion[1] + motion[2] * arm[0]

    speed_a, speed_b = point_velocity(velocity_a, position_a), point_velocity(velocity_b, position_b)
    relative = (speed_b[0] - speed_a[0], speed_b[1] - speed_a[1])
    length = _one_or(jnp.sqrt(relative[0] ** 2 + relative[1] ** 2))
    direction = (relative[0] / length, relative[1] / length)
    denominator = _one_or(
        _one_or(ma + mb) + (_cross(lever_a, direction) ** 2 * ia + _cross(lever_b, direction) ** 2 * ib)
    )
    return tuple((relative[k] + GAP_VELOCITY_RATE * gap[k]) / denominator * IMPULSE_SHARE for k in range(2))


def _angular_impulse(row: JointRows, frame: JointFrames, relative_turn):
    """The angular impulse on body a: a fixed joint turns back to its reference angle, a joint past a limit turns
    back unless already turning back (`relative_turn`: b's angular velocity less a's)."""
    ia, ib = row.response_a[2], row.response_b[2]
    angle = frame.angle
    excess = angle - jnp.clip(angle, row.lower_angle, row.upper_angle)
    fixed = row.solve_angle
    limit_turn = (jnp.sign(relative_turn) == jnp.sign(excess * LIMIT_ANGLE_RATE)) * (
        relative_turn + excess * LIMIT_ANGLE_RATE
    )
    turn_change = jnp.where(fixed, relative_turn + angle * FIXED_ANGLE_RATE, limit_turn)
    angular_impulse = turn_change / _one_or(ia + ib)
    applies_angular = fixed | (row.solve_limits & (excess != 0.0))
    return jnp.where(applies_angular, angular_impulse, 0.0)


def _add_to_bodies(values, mask_a, mask_b, change_a, change_b):
    """Each of `values` ((N+1, *batch) arrays) with `change_a` added at body a and `change_b` at body b."""
    return tuple(
        v + jnp.where(mask_a, da[None], 0.0) + jnp.where(mask_b, db[None], 0.0)
        for v, da, db in zip(values, change_a, change_b, strict=True)
    )


def _solve_one(velocity, pose, row: JointRows, frame: JointFrames, linear, angular):
    """One joint's pass: the velocities and poses after it, and its impulses (soft-law convention) after it."""
    mask_a, mask_b = frame.mask_a, frame.mask_b
    ma, ia = row.response_a[0], row.response_a[2]
    mb, ib = row.response_b[0], row.response_b[2]
    position_a, position_b = _select_motion(pose, mask_a)[:2], _select_motion(pose, mask_b)[:2]
    velocity_a, velocity_b = _select_motion(velocity, mask_a), _select_motion(velocity, mask_b)
    anchor_gap = tuple(position_b[k] + frame.lever_b[k] - (position_a[k] + frame.lever_a[k]) for k in range(2))
    impulse = _point_impulse(row, frame, (position_a, velocity_a), (position_b, velocity_b), anchor_gap)
    turn_a = _cross(frame.lever_a, impulse) * ia
    turn_b = -_cross(frame.lever_b, impulse) * ib
    angular_impulse = _angular_impulse(row, frame, velocity_b[2] + turn_b - velocity_a[2] - turn_a)
    turn_a = turn_a + angular_impulse * ia
    turn_b = turn_b - angular_impulse * ib
    solve = row.solve_point

    def gated(x):
        return jnp.where(solve, x, 0.0)

    inverse_mass_sum = _one_or(ma + mb)
    change_a = (gated(ma * impulse[0]), gated(ma * impulse[1]), gated(turn_a))
    change_b = (gated(-mb * impulse[0]), gated(-mb * impulse[1]), gated(turn_b))
    move_a = tuple(gated(anchor_gap[k] / inverse_mass_sum * ma * GAP_POSITION_SHARE) for k in range(2))
    move_b = tuple(gated(-anchor_gap[k] / inverse_mass_sum * mb * GAP_POSITION_SHARE) for k in range(2))
    velocity = _add_to_bodies(velocity, mask_a, mask_b, change_a, change_b)
    moved = _add_to_bodies(pose[:2], mask_a, mask_b, move_a, move_b)
    # Stored as the impulse on b: Jax2D's accumulated impulse acts on a, negated on b.
    linear = jnp.stack([linear[0] - gated(impulse[0]), linear[1] - gated(impulse[1])])
    angular = jnp.where(solve & row.solve_angle, angular - angular_impulse, 0.0)
    return velocity, (*moved, pose[2]), linear, angular


def solve_joints_jax2d(velocity, pose, rows: JointRows, frames: JointFrames, impulses: JointImpulses):
    """One pass over the joints in index order under Jax2D's law; `frames` at the step's start (rotations do not
    change within a step under this law). Returns the velocities, the poses and the joints' impulses."""
    linear, angular = impulses.linear, impulses.angular
    new_linear, new_angular = [], []
    for j in range(rows.body_a.shape[0]):
        row = _take(rows, j)
        frame = _take(frames, j)
        velocity, pose, joint_linear, joint_angular = _solve_one(velocity, pose, row, frame, linear[j], angular[j])
        new_linear.append(joint_linear)
        new_angular.append(joint_angular)
    if not new_linear:
        return velocity, pose, impulses
    return velocity, pose, impulses.replace(linear=jnp.stack(new_linear), angular=jnp.stack(new_angular))
