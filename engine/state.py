"""Simulator state: fixed-shape struct-of-arrays with active masks, one layout per `StaticSimParams`."""

from __future__ import annotations

import jax.numpy as jnp
from flax import struct

from kforge.engine.pairs import pair_layout
from kforge.engine.params import MAX_POLYGON_VERTICES, StaticSimParams

MAX_CONTACT_POINTS = 2
"""Contact points kept per shape pair (polygon pairs use both, pairs with a circle only the first)."""

NO_FEATURE = -1
"""Contact feature id of a contact point slot that holds no point."""


@struct.dataclass
class Bodies:
    """All shapes, shape N = num_polygons + num_circles: polygons in slots [0, P), circles in [P, N)."""

    position: jnp.ndarray  # (N, 2) f32 [m] world position of the centre of mass
    rotation: jnp.ndarray  # (N,) f32 [rad] counter-clockwise, never wrapped
    velocity: jnp.ndarray  # (N, 2) f32 [m/s] of the centre of mass
    angular_velocity: jnp.ndarray  # (N,) f32 [rad/s] counter-clockwise
    inverse_mass: jnp.ndarray  # (N,) f32 [1/kg]; 0 = static (immovable)
    inverse_inertia: jnp.ndarray  # (N,) f32 [1/(kg m^2)] about the centre of mass; 0 = cannot rotate
    friction: jnp.ndarray  # (N,) f32 [-] friction coefficient of the shape's surface
    restitution: jnp.ndarray  # (N,) f32 [-] in [0, 1]
    collision_mode: jnp.ndarray  # (N,) i32: 0 hits only mode 2, 1 hits modes 1 and 2, 2 hits everything
    active: jnp.ndarray  # (N,) bool: slot in use; inactive slots are ignored by physics
    n_vertices: jnp.ndarray  # (N,) i32: 3 or 4 for polygons, 0 for circles
    vertices: jnp.ndarray  # (N, 4, 2) f32 [m] body frame, relative to the centre of mass, counter-clockwise
    radius: jnp.ndarray  # (N,) f32 [m] circle radius; 0 for polygons

    @property
    def is_static(self) -> jnp.ndarray:
        """(N,) bool: bodies that never move."""
        return self.inverse_mass == 0.0


@struct.dataclass
class StartBodies:
    """The bodies at the start of a step, as the solver reads them: N+1 rows, the last a dummy body that colour padding
    reads and writes (zero, never moves)."""

    velocity: jnp.ndarray  # (N+1, 3) vx [m/s], vy [m/s], w [rad/s]
    pose: jnp.ndarray  # (N+1, 3) x [m], y [m], rotation [rad]
    acceleration: jnp.ndarray  # (N+1, 3) from gravity and thrusters, held over the step; 0 if it cannot move
    movable: jnp.ndarray  # (N+1,) bool: active and not static
    active: jnp.ndarray  # (N+1,) bool
    response_scale: jnp.ndarray  # (N+1, 3) inverse mass, inverse mass, inverse inertia; 0 if it cannot move


@struct.dataclass
class Joints:
    """Revolute and fixed joints, shape J."""

    body_a: jnp.ndarray  # (J,) i32 global body index
    body_b: jnp.ndarray  # (J,) i32 global body index
    anchor_a: jnp.ndarray  # (J, 2) f32 [m] joint point in body a's frame, relative to its centre of mass
    anchor_b: jnp.ndarray  # (J, 2) f32 [m] joint point in body b's frame
    reference_angle: jnp.ndarray  # (J,) f32 [rad] rotation_b - rotation_a at which the joint angle is 0
    active: jnp.ndarray  # (J,) bool
    is_fixed: jnp.ndarray  # (J,) bool: fixed (weld) joint; otherwise revolute
    motor_on: jnp.ndarray  # (J,) bool (revolute only); a motor acts only while its action is non-zero
    motor_speed: jnp.ndarray  # (J,) f32 [-] target speed in units of SimParams.base_motor_speed
    motor_power: jnp.ndarray  # (J,) f32 [-] torque bound in units of SimParams.base_motor_power
    has_limits: jnp.ndarray  # (J,) bool (revolute only)
    lower_angle: jnp.ndarray  # (J,) f32 [rad] joint-angle limit, <= 0
    upper_angle: jnp.ndarray  # (J,) f32 [rad] joint-angle limit, >= 0
    linear_impulse: jnp.ndarray  # (J, 2) f32 [N s] per substep, kept for warm starting
    angular_impulse: jnp.ndarray  # (J,) f32 [N m s] fixed-joint angular impulse per substep
    motor_impulse: jnp.ndarray  # (J,) f32 [N m s] motor impulse per substep
    limit_impulse: jnp.ndarray  # (J, 2) f32 [N m s] lower and upper limit impulses per substep


@struct.dataclass
class Thrusters:
    """Thrusters, shape T: a force on a body along a direction fixed in the body frame."""

    body: jnp.ndarray  # (T,) i32 global body index
    anchor: jnp.ndarray  # (T, 2) f32 [m] point of application in the body frame, relative to the centre of mass
    angle: jnp.ndarray  # (T,) f32 [rad] thrust direction in the body frame (0 = body +x)
    power: jnp.ndarray  # (T,) f32 [-] force in units of SimParams.base_thruster_power
    active: jnp.ndarray  # (T,) bool


@struct.dataclass
class ContactCache:
    """Impulses of last step's contact points, matched by feature id for warm starting; shape (K, 2).

    K is the number of candidate shape pairs of the static size (`engine.pairs.pair_layout`).
    """

    normal_impulse: jnp.ndarray  # (K, 2) f32 [N s] per substep
    tangent_impulse: jnp.ndarray  # (K, 2) f32 [N s] per substep
    feature: jnp.ndarray  # (K, 2) i32 geometric feature of each point; NO_FEATURE = empty


@struct.dataclass
class SimState:
    """Everything the simulator needs to continue: bodies, joints, thrusters, warm-start cache, gravity."""

    bodies: Bodies
    joints: Joints
    thrusters: Thrusters
    contacts: ContactCache
    collision_matrix: jnp.ndarray  # (N, N) bool: True where a pair may collide (False inside joint-connected groups)
    gravity: jnp.ndarray  # (2,) f32 [m/s^2]


def empty_state(static: StaticSimParams) -> SimState:
    """A state with every slot inactive, zero-filled, and default gravity (0, -9.81) m/s^2."""
    n, j, t = static.num_bodies, static.num_joints, static.num_thrusters
    k = pair_layout(static).num_pairs
    f32 = jnp.float32
    bodies = Bodies(
        position=jnp.zeros((n, 2), f32),
        rotation=jnp.zeros((n,), f32),
        velocity=jnp.zeros((n, 2), f32),
        angular_velocity=jnp.zeros((n,), f32),
        inverse_mass=jnp.zeros((n,), f32),
        inverse_inertia=jnp.zeros((n,), f32),
        friction=jnp.zeros((n,), f32),
        restitution=jnp.zeros((n,), f32),
        collision_mode=jnp.ones((n,), jnp.int32),
        active=jnp.zeros((n,), bool),
        n_vertices=jnp.zeros((n,), jnp.int32),
        vertices=jnp.zeros((n, MAX_POLYGON_VERTICES, 2), f32),
        radius=jnp.zeros((n,), f32),
    )
    joints = Joints(
        body_a=jnp.zeros((j,), jnp.int32),
        body_b=jnp.zeros((j,), jnp.int32),
        anchor_a=jnp.zeros((j, 2), f32),
        anchor_b=jnp.zeros((j, 2), f32),
        reference_angle=jnp.zeros((j,), f32),
        active=jnp.zeros((j,), bool),
        is_fixed=jnp.zeros((j,), bool),
        motor_on=jnp.zeros((j,), bool),
        motor_speed=jnp.zeros((j,), f32),
        motor_power=jnp.zeros((j,), f32),
        has_limits=jnp.zeros((j,), bool),
        lower_angle=jnp.zeros((j,), f32),
        upper_angle=jnp.zeros((j,), f32),
        linear_impulse=jnp.zeros((j, 2), f32),
        angular_impulse=jnp.zeros((j,), f32),
        motor_impulse=jnp.zeros((j,), f32),
        limit_impulse=jnp.zeros((j, 2), f32),
    )
    thrusters = Thrusters(
        body=jnp.zeros((t,), jnp.int32),
        anchor=jnp.zeros((t, 2), f32),
        angle=jnp.zeros((t,), f32),
        power=jnp.zeros((t,), f32),
        active=jnp.zeros((t,), bool),
    )
    contacts = ContactCache(
        normal_impulse=jnp.zeros((k, MAX_CONTACT_POINTS), f32),
        tangent_impulse=jnp.zeros((k, MAX_CONTACT_POINTS), f32),
        feature=jnp.full((k, MAX_CONTACT_POINTS), NO_FEATURE, jnp.int32),
    )
    return SimState(
        bodies=bodies,
        joints=joints,
        thrusters=thrusters,
        contacts=contacts,
        collision_matrix=~jnp.eye(n, dtype=bool),
        gravity=jnp.array([0.0, -9.81], f32),
    )
