"""One physics step: narrowphase once, then soft substeps (Box2D v3 style), restitution and safety clips."""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
from flax import struct

from kforge.engine.batch_last import Batching, vmap_batch_last, vmap_in_chunks
from kforge.engine.collision import (
    Manifolds,
    circle_contact_clearance,
    manifolds,
    world_geometry,
)
from kforge.engine.collision_filter import modes_collide
from kforge.engine.contact_solver import (
    NUM_POINTS,
    ContactGeometry,
    ContactImpulses,
    ContactPass,
    ContactRows,
    PairConstants,
    PushLaw,
    apply_restitution,
    bounces_anywhere,
    build_rows,
    from_colour_layout,
    prepare_contacts,
    solve_contacts,
    to_colour_layout,
    warm_start_contacts,
)
from kforge.engine.geometry import cross2, dot2, norm2, rotate
from kforge.engine.jax2d_contacts import solve_contacts_jax2d, solver_batches
from kforge.engine.jax2d_joints import solve_joints_jax2d
from kforge.engine.joint_solver import (
    JointFrames,
    JointImpulses,
    JointPass,
    JointRows,
    joint_frames,
    prepare_joints,
    servo_motor_kick,
    solve_joints,
    warm_start_joints,
)
from kforge.engine.pairs import PairLayout, pair_layout
from kforge.engine.params import (
    CollisionRules,
    ContactLaw,
    ContactOrder,
    ContactPoints,
    ForceTiming,
    JointLaw,
    MotorLaw,
    SimParams,
    StaticSimParams,
)
from kforge.engine.softness import Softness, make_softness
from kforge.engine.state import NO_FEATURE, Bodies, ContactCache, Joints, SimState, StartBodies
from kforge.engine.sweep import SWEEPS, Motion, Sweep

STATIC_CONTACT_STIFFNESS_FACTOR = 2.0
"""Contacts against static bodies are this many times stiffer (in Hz) than between movable bodies."""


@struct.dataclass
class StepInfo:
    """What happened during a step, per candidate pair (layout of `engine.pairs.pair_layout`)."""

    # (K,) bool: both shapes active, their collision modes allow contact, and closer than touch_distance at step start
    # or pushed apart by their contact during the step (a speculative contact that acted: in Kinetix, which has none,
    # the shapes would have overlapped); joints are ignored at step start (as in Kinetix), so jointed shapes that
    # overlap count as touching.
    touching: jnp.ndarray
    separation: jnp.ndarray  # (K,) [m] smallest separation of the pair's contact points (inf when none)


def _bounding_radius(bodies):
    squared = dot2(bodies.vertices, bodies.vertices)
    polygon_radius = jnp.sqrt(functools.reduce(jnp.maximum, [squared[:, i] for i in range(squared.shape[1])]))
    return jnp.where(bodies.n_vertices > 0, polygon_radius, bodies.radius)


def match_warm_start(cache: ContactCache, feature, by_slot: bool):
    """Last step's impulses for points whose feature id reappears (in either point slot); with `by_slot` (static),
    for points whose slot held a point last step (Jax2D's)."""

    def pick(values):
        found = feature >= 0
        if by_slot:
            return jnp.where(found & (cache.feature >= 0), values, 0.0)
        match0 = feature == cache.feature[:, :1]
        match1 = feature == cache.feature[:, 1:]
        return jnp.where(found & match0, values[:, :1], jnp.where(found & match1, values[:, 1:], 0.0))

    return pick(cache.normal_impulse), pick(cache.tangent_impulse)


@struct.dataclass
class SolverScalars:
    """Per-scene scalars of the substep solver."""

    substep: jnp.ndarray  # [s]
    inverse_substep: jnp.ndarray  # [1/s]
    max_push_velocity: jnp.ndarray  # [m/s]
    restitution_threshold: jnp.ndarray  # [m/s]
    joint_softness: Softness
    push_law: PushLaw


@struct.dataclass
class SolverInput:
    """Bodies (N+1 rows: the last is a dummy for colour padding) and constraints entering the substeps."""

    velocity: jnp.ndarray  # (N+1, 3) vx [m/s], vy [m/s], w [rad/s]; under STEP_START after the step's forces
    pose: jnp.ndarray  # (N+1, 3) x [m], y [m], rotation [rad]
    acceleration: jnp.ndarray  # (N+1, 3) from gravity and thrusters, zero for bodies that cannot move
    movable: jnp.ndarray  # (N+1,) bool
    response_scale: jnp.ndarray  # (N+1, 3) inverse mass, inverse mass, inverse inertia; 0 if it cannot move
    contact_geometry: ContactGeometry
    contact_impulses: ContactImpulses
    joint_rows: JointRows
    joint_impulses: JointImpulses
    scalars: SolverScalars


@struct.dataclass
class SolverOutput:
    velocity: jnp.ndarray  # (N+1, 3)
    pose: jnp.ndarray  # (N+1, 3)
    contact_impulses: ContactImpulses
    joint_impulses: JointImpulses


@struct.dataclass
class Prepared:
    """Result of `prepare_step`."""

    solver_input: SolverInput
    info: StepInfo
    point_enabled: jnp.ndarray  # (K, 2) bool
    feature: jnp.ndarray  # (K, 2) i32


def spread_force_share(index) -> jnp.ndarray:
    """The substeps' worth of gravity and thrust that substep `index` (traced) adds under `ForceTiming.SPREAD`: 1.

    A selection on the index: a constant share would be hoisted out of the substep loop, and the update's product
    rounded apart from its sum, changing the step's bits (1 ulp)."""
    return jnp.where(index >= 0, 1, 0)


@dataclasses.dataclass(frozen=True)
class _Substeps:
    """What every solver pass of one step reads: the laws and counts (static), the sweep's form, the constraint rows,
    the poses at the step's start and, with one substep, the joints' frames at them."""

    static: StaticSimParams
    layout: PairLayout
    sweep: Sweep
    unrolled: bool  # the substeps and passes written out, not looped
    rows: ContactRows
    geometry: ContactGeometry  # the rows' geometry (rebuilt from moved bodies under Jax2D's joint law)
    response_scale: jnp.ndarray  # (N+1, 3, *batch)
    joint_rows: JointRows
    scalars: SolverScalars
    acceleration: Motion
    movable: jnp.ndarray  # (N+1, *batch) bool
    start_pose: Motion
    start_frames: JointFrames | None  # with one substep: the position-correcting passes all see the starting poses

    def frames_at(self, pose: Motion, use_bias: bool) -> JointFrames:
        """The joints' frames at `pose` (the starting ones for a position-correcting pass of a single substep)."""
        if self.start_frames is not None and use_bias:
            return self.start_frames
        return joint_frames(self.joint_rows, pose, self.start_pose[2])

    def joint_pass(self, use_bias: bool) -> JointPass:
        """How a pass solves the joints."""
        constraint_motors = self.static.motor_law == MotorLaw.CONSTRAINT
        scalars = self.scalars
        return JointPass(
            softness=scalars.joint_softness,
            inverse_substep=scalars.inverse_substep,
            use_bias=use_bias,
            constraint_motors=constraint_motors,
            sweep=self.sweep,
        )

    def contact_pass(self, use_bias: bool) -> ContactPass:
        """How a pass solves the contacts."""
        baumgarte, block = self.static.contact_law == ContactLaw.BAUMGARTE, self.static.block_contacts
        scalars = self.scalars
        return ContactPass(
            inverse_substep=scalars.inverse_substep,
            max_push_velocity=scalars.max_push_velocity,
            use_bias=use_bias,
            baumgarte_law=baumgarte,
            push_law=scalars.push_law,
            block=block,
            sweep=self.sweep,
        )


def _rows_at(substeps: _Substeps, pose: Motion) -> ContactRows:
    """The contact rows with each point's levers from its bodies' current positions (Jax2D's contacts read the
    positions that its joints moved within the step)."""
    layout = substeps.layout
    shift = [p - s for p, s in zip(pose[:2], substeps.start_pose[:2], strict=True)]
    geometry = substeps.geometry

    def moved_lever(lever, bodies):
        along = jnp.stack([component[bodies] for component in shift], axis=2)  # (C, W, 2, *batch)
        return lever - along[:, :, None]

    geometry = geometry.replace(
        lever_a=moved_lever(geometry.lever_a, layout.colour_body_a),
        lever_b=moved_lever(geometry.lever_b, layout.colour_body_b),
    )
    return build_rows(geometry, substeps.response_scale, layout)


def _solver_pass(substeps: _Substeps, carry, use_bias: bool, advance: bool, contacts: bool = True):
    """Joints then, if `contacts`, contacts; then, if `advance`, integrate positions. `carry`: velocities, poses,
    contact and joint impulses."""
    velocity, pose, contact_impulses, joint_impulses = carry
    if substeps.static.joint_law == JointLaw.JAX2D:
        frames = substeps.frames_at(substeps.start_pose, True)
        velocity, pose, joint_impulses = solve_joints_jax2d(velocity, pose, substeps.joint_rows, frames, joint_impulses)
    else:
        frames = substeps.frames_at(pose, use_bias)
        velocity, joint_impulses = solve_joints(
            velocity, substeps.joint_rows, frames, joint_impulses, substeps.joint_pass(use_bias)
        )
    if contacts:
        unmoved = substeps.start_frames is not None and use_bias
        moved = None if unmoved else tuple(p - s for p, s in zip(pose, substeps.start_pose, strict=True))
        settings = substeps.contact_pass(use_bias)
        rows = substeps.rows
        if substeps.static.joint_law == JointLaw.JAX2D:
            rows = _rows_at(substeps, pose)
        if substeps.static.contact_order == ContactOrder.JAX2D:
            batches = substeps.geometry.batch
            velocity, contact_impulses = solve_contacts_jax2d(
                velocity, rows, contact_impulses, substeps.layout, batches, settings
            )
        else:
            velocity, contact_impulses = solve_contacts(
                velocity, moved, rows, contact_impulses, substeps.layout, settings
            )
    step_length, move = substeps.scalars.substep, substeps.movable
    pose = tuple(jnp.where(move & advance, p + step_length * v, p) for p, v in zip(pose, velocity, strict=True))
    return velocity, pose, contact_impulses, joint_impulses


def _substep(substeps: _Substeps, carry, index):
    """Integrate velocities, warm start, soft solve, integrate positions, then relax without bias."""
    static, scalars = substeps.static, substeps.scalars
    velocity, pose, contact_impulses, joint_impulses = carry
    if static.force_timing == ForceTiming.SPREAD:  # STEP_START: in the solver's starting velocities
        share = spread_force_share(index) * scalars.substep
        velocity = tuple(v + share * a for v, a in zip(velocity, substeps.acceleration, strict=True))
    velocity = warm_start_joints(velocity, substeps.joint_rows, substeps.frames_at(pose, True), joint_impulses)
    velocity = warm_start_contacts(velocity, substeps.rows, contact_impulses, substeps.layout)
    carry = (velocity, pose, contact_impulses, joint_impulses)
    if static.num_iterations > 1:
        carry, _ = jax.lax.scan(
            lambda c, _: (_solver_pass(substeps, c, True, False), None),
            carry,
            None,
            length=static.num_iterations - 1,
            unroll=substeps.unrolled,
        )
    carry = _solver_pass(substeps, carry, True, True)
    for _ in range(static.num_relax_iterations):
        carry = _solver_pass(substeps, carry, False, False, static.relax_contacts)
    return carry, None


def _components(x) -> tuple:
    return tuple(x[:, k] for k in range(x.shape[1]))


def _solve(static: StaticSimParams, solver_loops: str, skip_idle_bounce: bool, solver_input: SolverInput):
    """The substeps and restitution of one step (rank-polymorphic: any trailing batch axes)."""
    layout = pair_layout(static)
    sweep = SWEEPS["looped" if solver_loops == "looped" else "unrolled"]
    velocity, start_pose = _components(solver_input.velocity), _components(solver_input.pose)
    rows = build_rows(solver_input.contact_geometry, solver_input.response_scale, layout)
    joint_rows, scalars = solver_input.joint_rows, solver_input.scalars
    unmoved = static.num_substeps == 1
    substeps = _Substeps(
        static=static,
        layout=layout,
        sweep=sweep,
        unrolled=solver_loops == "unrolled",
        rows=rows,
        geometry=solver_input.contact_geometry,
        response_scale=solver_input.response_scale,
        joint_rows=joint_rows,
        scalars=scalars,
        acceleration=_components(solver_input.acceleration),
        movable=solver_input.movable,
        start_pose=start_pose,
        start_frames=joint_frames(joint_rows, start_pose, start_pose[2]) if unmoved else None,
    )
    carry = (velocity, start_pose, solver_input.contact_impulses, solver_input.joint_impulses)
    (velocity, pose, contact_impulses, joint_impulses), _ = jax.lax.scan(
        functools.partial(_substep, substeps), carry, jnp.arange(static.num_substeps), unroll=substeps.unrolled
    )
    threshold = scalars.restitution_threshold

    def bounce(velocity, contact_impulses):
        return apply_restitution(velocity, rows, contact_impulses, layout, threshold, sweep)

    if skip_idle_bounce:  # one decision for the whole (batch-last) batch
        bounces = bounces_anywhere(rows, contact_impulses, threshold)
        velocity, contact_impulses = jax.lax.cond(bounces, bounce, lambda *carry: carry, velocity, contact_impulses)
    else:
        velocity, contact_impulses = bounce(velocity, contact_impulses)
    return SolverOutput(jnp.stack(velocity, 1), jnp.stack(pose, 1), contact_impulses, joint_impulses)


@functools.cache
def substep_solver(static: StaticSimParams, batch_last: bool = True, solver_loops: str = "looped"):
    """The substep loop and restitution for `static`: `SolverInput -> SolverOutput`, batch-last under vmap if asked,
    with its loops (substeps, passes, Gauss-Seidel sweeps) in the form `solver_loops` (one of
    `engine.batch_last.SOLVER_LOOP_FORMS`).

    A substep runs `num_iterations` passes with position bias (all but the last in a `lax.scan`), advances the
    positions after the last, then `num_relax_iterations` passes without bias, of joints only unless `relax_contacts`
    (soft step: 1, 1; Jax2D's scheme: 10 iterations in one substep and no relaxing pass). With one substep the
    position-correcting passes all see the step's starting poses (positions advance after the last): their joint
    frames are computed once, and their contacts have moved nowhere. Looped, substeps, passes, joints and colours are
    `lax.scan`s, so the compiled size does not grow with their number; unrolled, they are written out in order (fewer
    kernels, a larger program); "unrolled_sweeps" writes out joints and colours only. Joints' warm starting (nothing
    solved) is unrolled into one fusion either way. Batch-last, the restitution sweep runs only when some point of
    the batch bounces. The laws of `static` are chosen here, in Python: the program holds only their kernels.
    """
    solve = functools.partial(_solve, static, solver_loops, batch_last)
    return vmap_batch_last(solve) if batch_last else solve


def _external_acceleration(state: SimState, params: SimParams, thruster_actions, movable, response_scale):
    """(N+1, 3) acceleration of each body from gravity and thrusters, held over the step; 0 if it cannot move."""
    bodies, thrusters = state.bodies, state.thrusters
    n = bodies.active.shape[0]
    rotation = bodies.rotation[thrusters.body]
    thrust_angle = rotation + thrusters.angle
    strength = params.base_thruster_power * thrusters.power * jnp.clip(thruster_actions, 0.0, 1.0) * thrusters.active
    thrust = strength[:, None] * jnp.stack([jnp.cos(thrust_angle), jnp.sin(thrust_angle)], -1)
    torque = cross2(rotate(rotation, thrusters.anchor), thrust)
    owner = (thrusters.body[:, None] == jnp.arange(n + 1)).astype(thrust.dtype)
    external = owner.T @ jnp.concatenate([thrust, torque[:, None]], -1)
    gravity = jnp.concatenate([state.gravity, jnp.zeros(1)])
    return jnp.where(movable[:, None], response_scale * external + gravity, 0.0)


def _step_start_velocity(state: SimState, params: SimParams, start: StartBodies, thruster_actions) -> jnp.ndarray:
    """(N+1, 3) velocities after the whole step's gravity, then thrust, in Jax2D's arithmetic
    (`ForceTiming.STEP_START`): v + g dt, then a thruster's impulse power x base power x action x dt along its
    direction."""
    bodies, thrusters = state.bodies, state.thrusters
    n = bodies.active.shape[0]
    gravity = jnp.concatenate([state.gravity * params.dt, jnp.zeros(1)])
    velocity = jnp.where(start.movable[:, None], start.velocity + gravity, start.velocity)
    rotation = bodies.rotation[thrusters.body]
    lever = rotate(rotation, thrusters.anchor)
    angle = thrusters.angle + rotation
    direction = jnp.stack([jnp.cos(angle), jnp.sin(angle)], -1)
    action = jnp.clip(thruster_actions, 0.0, 1.0)
    force = thrusters.power * thrusters.active * params.base_thruster_power * action * params.dt
    response = start.response_scale[thrusters.body]
    change = jnp.concatenate(
        [response[:, :2] * direction * force[:, None], (response[:, 2] * cross2(lever, direction) * force)[:, None]], -1
    )
    for k in range(thrusters.body.shape[0]):
        velocity = jnp.where((jnp.arange(n + 1) == thrusters.body[k])[:, None], velocity + change[k], velocity)
    return velocity


def _extend(x):
    """`x` with a zero row appended: row N is a dummy body that colour padding reads and writes."""
    return jnp.concatenate([x, jnp.zeros((1,) + x.shape[1:], x.dtype)])


def _start_bodies(state: SimState, params: SimParams, motor_actions, thruster_actions, static: StaticSimParams):
    """The bodies at the start of the step (N+1 rows), after the servo motors' kick under `MotorLaw.SERVO`."""
    bodies = state.bodies
    movable = _extend(bodies.active & ~bodies.is_static)
    inverse_masses = jnp.stack([bodies.inverse_mass, bodies.inverse_mass, bodies.inverse_inertia], -1)
    response_scale = jnp.where(movable[:, None], _extend(inverse_masses), 0.0)
    start = StartBodies(
        velocity=_extend(jnp.concatenate([bodies.velocity, bodies.angular_velocity[:, None]], -1)),
        pose=_extend(jnp.concatenate([bodies.position, bodies.rotation[:, None]], -1)),
        acceleration=_external_acceleration(state, params, thruster_actions, movable, response_scale),
        movable=movable,
        active=_extend(bodies.active),
        response_scale=response_scale,
    )
    if static.motor_law == MotorLaw.SERVO:
        kick = servo_motor_kick(state.joints, start, motor_actions, params)
        start = start.replace(velocity=start.velocity.at[:, 2].add(kick))
    return start


def _contact_margin(bodies: Bodies, start: StartBodies, params: SimParams, layout: PairLayout):
    """(K,) [m] each pair's speculative distance: the base distance plus its share of this step's motion."""
    n = layout.num_bodies
    a, b = layout.body_a, layout.body_b
    velocity, acceleration = start.velocity, start.acceleration
    reach = norm2(velocity[:n, :2]) + jnp.abs(velocity[:n, 2]) * _bounding_radius(bodies)
    reach = reach + params.dt * norm2(acceleration[:n, :2])
    motion = params.dt * (reach[a] + reach[b])
    return params.speculative_distance + params.speculative_reach * motion


def _touching(state: SimState, manifold: Manifolds, params: SimParams, layout: PairLayout) -> StepInfo:
    """Which pairs touch at the step's start, and their smallest separation."""
    bodies = state.bodies
    a, b = layout.body_a, layout.body_b
    both_active = bodies.active[a] & bodies.active[b]
    modes = modes_collide(bodies.collision_mode[a], bodies.collision_mode[b])
    present = manifold.valid & both_active[:, None]
    touch = present & (manifold.separation < params.touch_distance)
    point_separation = jnp.where(present, manifold.separation, jnp.inf)
    return StepInfo(
        touching=modes & (touch[:, 0] | touch[:, 1]),
        separation=jnp.minimum(point_separation[:, 0], point_separation[:, 1]),
    )


def _pair_constants(bodies: Bodies, state: SimState, params: SimParams, substep, layout: PairLayout) -> PairConstants:
    """Whether each candidate pair may collide this step, and its mixed friction, restitution and softness."""
    a, b = layout.body_a, layout.body_b
    static_body = bodies.is_static
    both_active = bodies.active[a] & bodies.active[b]
    modes = modes_collide(bodies.collision_mode[a], bodies.collision_mode[b])
    softness = make_softness(params.contact_hertz, params.contact_damping_ratio, substep)
    static_softness = make_softness(
        STATIC_CONTACT_STIFFNESS_FACTOR * params.contact_hertz, params.contact_damping_ratio, substep
    )
    pair_static = static_body[a] | static_body[b]
    return PairConstants(
        enabled=both_active & modes & state.collision_matrix[a, b] & ~(static_body[a] & static_body[b]),
        friction=params.base_friction * jnp.sqrt(bodies.friction[a] ** 2 + bodies.friction[b] ** 2),
        restitution=jnp.minimum(bodies.restitution[a], bodies.restitution[b]),
        softness=jax.tree_util.tree_map(lambda s, h: jnp.where(pair_static, h, s), softness, static_softness),
    )


def _contact_constraints(state: SimState, start: StartBodies, params: SimParams, static: StaticSimParams):
    """Narrowphase with a speculative margin covering this step's motion, then the contact rows, warm-started from
    last step's impulses of the same features: (contact geometry, impulses, touching info, manifolds, points
    enabled)."""
    layout = pair_layout(static)
    n = static.num_bodies
    bodies = state.bodies
    geometry = world_geometry(bodies)
    margin = _contact_margin(bodies, start, params, layout)
    jax2d_rules = static.collision_rules == CollisionRules.JAX2D
    manifold = manifolds(geometry, layout, margin, static.contact_points == ContactPoints.KINETIX, jax2d_rules)
    info = _touching(state, manifold, params, layout)
    pairs = _pair_constants(bodies, state, params, params.dt / static.num_substeps, layout)
    # A circle's speculative contact is dropped when free motion carries it past what it faces (a near miss).
    if static.swept_speculative_contacts:
        check_times = [0.5 * params.dt, params.dt]
        velocity, acceleration = start.velocity[:n], start.acceleration[:n]
        misses = circle_contact_clearance(manifold, geometry, layout, velocity, acceleration, check_times)
        manifold = manifold.replace(valid=manifold.valid & ~misses[:, None])
    point_enabled = manifold.valid & pairs.enabled[:, None]
    contact_geometry = prepare_contacts(
        manifold, pairs, start.pose[:n, :2], start.velocity[:n], start.acceleration[:n], layout
    )
    if static.contact_order == ContactOrder.JAX2D:
        a, b = layout.body_a, layout.body_b
        modes = modes_collide(bodies.collision_mode[a], bodies.collision_mode[b])
        counted = manifold.valid.any(-1) & bodies.active[a] & bodies.active[b] & modes
        contact_geometry = contact_geometry.replace(batch=solver_batches(counted, layout))
    normal_warm, tangent_warm = match_warm_start(state.contacts, manifold.feature, jax2d_rules)
    warm = jnp.where(jnp.tile(point_enabled, (1, 2)), jnp.concatenate([normal_warm, tangent_warm], -1), 0.0)
    contact_impulses = to_colour_layout(
        ContactImpulses(
            impulse=tuple(warm[:, r] for r in range(warm.shape[1])),
            max_normal=tuple(jnp.zeros_like(normal_warm[:, p]) for p in range(normal_warm.shape[1])),
        ),
        layout,
    )
    return contact_geometry, contact_impulses, info, manifold, point_enabled


def _joint_constraints(joints: Joints, start: StartBodies, motor_actions, params: SimParams, static: StaticSimParams):
    """The joints' rows and warm-start impulses (a servo motor acted before)."""
    substep = params.dt / static.num_substeps
    joint_rows = prepare_joints(joints, start, motor_actions, params, substep, static.motor_law == MotorLaw.CONSTRAINT)
    joint_impulses = JointImpulses(
        linear=jnp.where(joints.active[:, None], joints.linear_impulse, 0.0),
        angular=jnp.where(joints.active, joints.angular_impulse, 0.0),
        motor=jnp.where(joint_rows.solve_motor, joints.motor_impulse, 0.0),
        limit=jnp.where(joint_rows.solve_limits[:, None], joints.limit_impulse, 0.0),
    )
    return joint_rows, joint_impulses


def _solver_scalars(params: SimParams, static: StaticSimParams) -> SolverScalars:
    substep = params.dt / static.num_substeps
    return SolverScalars(
        substep=substep,
        inverse_substep=1.0 / substep,
        max_push_velocity=params.max_push_velocity,
        restitution_threshold=params.restitution_threshold,
        joint_softness=make_softness(params.joint_hertz, params.joint_damping_ratio, substep),
        push_law=PushLaw(
            depth=params.baumgarte_depth,
            rate=params.baumgarte_share / params.dt,
            slop=params.contact_slop,
        ),
    )


def prepare_step(
    state: SimState, params: SimParams, motor_actions, thruster_actions, static: StaticSimParams
) -> Prepared:
    """Everything computed once per step before the substeps: manifolds, constraint rows, external accelerations."""
    start = _start_bodies(state, params, motor_actions, thruster_actions, static)
    contact_geometry, contact_impulses, info, manifold, point_enabled = _contact_constraints(
        state, start, params, static
    )
    joint_rows, joint_impulses = _joint_constraints(state.joints, start, motor_actions, params, static)
    velocity = start.velocity
    if static.force_timing == ForceTiming.STEP_START:
        velocity = _step_start_velocity(state, params, start, thruster_actions)
    solver_input = SolverInput(
        velocity=velocity,
        pose=start.pose,
        acceleration=start.acceleration,
        movable=start.movable,
        response_scale=start.response_scale,
        contact_geometry=contact_geometry,
        contact_impulses=contact_impulses,
        joint_rows=joint_rows,
        joint_impulses=joint_impulses,
        scalars=_solver_scalars(params, static),
    )
    return Prepared(solver_input, info, point_enabled, manifold.feature)


def finish_step(
    state: SimState, params: SimParams, prepared: Prepared, solved: SolverOutput, static: StaticSimParams
) -> SimState:
    """Write the solver's velocities, poses and impulses back into the state, with the safety clips."""
    layout = pair_layout(static)
    n = static.num_bodies
    bodies, joints = state.bodies, state.joints
    movable = prepared.solver_input.movable[:n]
    velocity, pose, joint_impulses = solved.velocity, solved.pose, solved.joint_impulses
    per_pair = from_colour_layout(solved.contact_impulses.impulse, layout)
    new_bodies = bodies.replace(
        position=jnp.where(
            movable[:, None], jnp.clip(pose[:n, :2], -params.max_position, params.max_position), bodies.position
        ),
        rotation=jnp.where(movable, pose[:n, 2], bodies.rotation),
        velocity=jnp.where(
            movable[:, None], jnp.clip(velocity[:n, :2], -params.max_velocity, params.max_velocity), bodies.velocity
        ),
        angular_velocity=jnp.where(
            movable,
            jnp.clip(velocity[:n, 2], -params.max_angular_velocity, params.max_angular_velocity),
            bodies.angular_velocity,
        ),
    )
    new_joints = joints.replace(
        linear_impulse=joint_impulses.linear,
        angular_impulse=joint_impulses.angular,
        motor_impulse=joint_impulses.motor,
        limit_impulse=joint_impulses.limit,
    )
    cache = ContactCache(
        normal_impulse=jnp.stack(per_pair[:NUM_POINTS], -1),
        tangent_impulse=jnp.stack(per_pair[NUM_POINTS:], -1),
        feature=jnp.where(prepared.point_enabled, prepared.feature, NO_FEATURE),
    )
    return state.replace(bodies=new_bodies, joints=new_joints, contacts=cache)


def _info_after_solve(prepared: Prepared, solved: SolverOutput, params: SimParams, static: StaticSimParams) -> StepInfo:
    """The step's `StepInfo`, counting as touching also the pairs whose contact pushed during the step from closer
    than `push_touch_distance` at its start."""
    largest = from_colour_layout(solved.contact_impulses.max_normal, pair_layout(static))
    pushed = functools.reduce(jnp.logical_or, [impulse > 0.0 for impulse in largest])
    pushed = pushed & (prepared.info.separation < params.push_touch_distance)
    return prepared.info.replace(touching=prepared.info.touching | pushed)


@functools.cache
def _batched_step(static: StaticSimParams, batching: Batching):
    """The step of `static` with the vmap rule of `batching` (`engine.batch_last`, resolved)."""

    def one_step(state, params, motor_actions, thruster_actions):
        prepared = prepare_step(state, params, motor_actions, thruster_actions, static)
        solved = substep_solver(static, batching.chunked, batching.solver_loops)(prepared.solver_input)
        return finish_step(state, params, prepared, solved, static), _info_after_solve(prepared, solved, params, static)

    return vmap_in_chunks(one_step, batching.chunk_limit) if batching.chunked else one_step


@functools.partial(jax.jit, static_argnames=("static", "batching"))
def _step(state, params, motor_actions, thruster_actions, static: StaticSimParams, batching: Batching):
    return _batched_step(static, batching)(state, params, motor_actions, thruster_actions)


def step(
    state: SimState,
    params: SimParams,
    motor_actions: jnp.ndarray,
    thruster_actions: jnp.ndarray,
    static: StaticSimParams,
) -> tuple[SimState, StepInfo]:
    """Advance `state` by `params.dt`.

    `motor_actions` (J,) in [-1, 1] scale each joint motor's target speed; `thruster_actions` (T,) in [0, 1]
    scale each thruster's force. Returns the new state and per-pair contact information. The laws and counts of
    `static` are compiled in; under `vmap`, how the batch is run (in chunks with batch-last layout, or as one vmap)
    and the form of the solver's loops (looped or unrolled) follow `static.batching`, "auto" resolved for the default
    backend when traced.
    """
    return _step(state, params, motor_actions, thruster_actions, static=static, batching=static.batching.resolved())
