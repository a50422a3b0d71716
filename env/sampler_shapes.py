"""Shape, joint and thruster proposals of the Kinetix random level distribution, and writing them into a level.

Every proposal reads its randomness from one row of uniform draws (`Draw` names the columns), so a batch of
proposals costs one PRNG call. Shapes are rectangles (centred on their centre of mass) or discs.
"""

from __future__ import annotations

import enum
import math

import jax.numpy as jnp
from flax import struct

from kforge.engine import (
    ARENA_SIZE,
    FLOOR_TOP,
    MAX_POLYGON_VERTICES,
    circle_mass_properties,
    modes_collide,
    polygon_mass_properties,
    rotate,
)
from kforge.env.params import NUM_MOTOR_BINDINGS, NUM_THRUSTER_BINDINGS, StaticEnvParams
from kforge.env.state import Level, Role

# Shape dimensions (Kinetix `sample_dimensions` with max_shape_size 1 m).
MIN_HALF_EXTENT = 0.05  # [m] smallest rectangle half side
MAX_HALF_EXTENT = 0.5 / math.sqrt(2.0)  # [m] largest rectangle half side before doubling
LARGE_SIDE_CHANCE = 0.3  # [-] probability that one rectangle side is scaled up
LARGE_SIDE_SCALE = 2.0  # [-] factor of that side
MIN_RADIUS = 0.1  # [m]
MAX_RADIUS = 0.4  # [m] (0.5 m * circle_max_size_coeff 0.8)

# Placement and material.
GOAL_SIDE_CHANCE = 0.5  # [-] probability that green is confined to the left half and blue to the right half
SHAPE_DENSITY = 1.0  # [kg/m^2]
DISC_INERTIA_SHARE = 0.25  # [-] a sampled disc's inertia per m r^2: Kinetix's sampler stores Jax2D's pi rho r^4 / 4
# (m r^2 / 4, mass gathered towards the centre; a uniform disc has m r^2 / 2), so sampled levels turn as Kinetix's do
SHAPE_FRICTION = 1.0  # [-]
SHAPE_COLLISION_MODE = 1  # collides with modes 1 and 2 (everything sampled, and the boundaries)

# Fixation (static shapes): probability min(1, FIXATE_CHANCE_MIN + FIXATE_CHANCE_PER_KG * mass).
FIXATE_CHANCE_MIN = 0.02  # [-]
FIXATE_CHANCE_PER_KG = 4.0  # [1/kg]
FIXATED_GOAL_LOWER_HALF_CHANCE = (
    0.6  # [-] a fixated green/blue/red shape in the upper half moves down by half the arena
)

# Roles.
RED_WEIGHT = 1.0 / 3.0  # [-] weight of red against default 1 while no red shape exists (red floor included)

# Connected shapes (Kinetix `mutate_add_connected_shape`).
CONNECT_TO_FIXATED_WEIGHT = 0.05  # [-] relative weight of a fixated target
MAX_POLYGON_JOINTS = 2  # a rectangle is a target for fewer than this many joints (weight falls linearly)
MIN_REVOLUTE_JOINTS = 2  # joints are revolute until this many revolute joints exist
REVOLUTE_CHANCE = 0.5  # [-] afterwards
MOTOR_ON_CHANCE = 0.8  # [-]
MOTOR_SPEED_RANGE = (0.4, 3.0)  # [-] in units of the base motor speed
MOTOR_POWER_RANGE = (1.0, 3.0)  # [-] in units of the base motor power, rectangle-rectangle joints
WHEEL_MOTOR_POWER = 1.0  # [-] when a circle is involved
JOINT_LIMIT_CHANCE = 0.4  # [-] rectangle-rectangle revolute joints only
JOINT_LIMIT_MAX = math.pi  # [rad] lower limit in [-max, 0], upper in [0, max]
VISIBILITY_MARGIN = 0.05  # [m] a jointed shape must stick out of its partner by this much to count as visible
HIDDEN_PENALTY = 10  # overlap-score penalty of a connected proposal in which one shape hides the other

# Thrusters (Kinetix `mutate_add_thruster`).
THRUSTER_ALIGN_CHANCE = 0.8  # [-] thrust along +-(anchor -> centre of mass) instead of a random direction
THRUSTER_POWER_PER_KG = 2.0  # [1/kg] power = mass * this * U[THRUSTER_SCALE_RANGE]
THRUSTER_SCALE_RANGE = (0.5, 2.0)  # [-]


class Draw(enum.IntEnum):
    """Columns of a shape proposal's row of U[0, 1) draws.

    Free and connected proposals of one step read the same row (only one of them is used): the last six
    columns serve free placement (GOAL_SIDE..LOWER_HALF) or the attachment (TARGET_KIND..TARGET_ANCHOR_Y).
    """

    KIND = 0
    ROLE = 1
    HALF_X = 2
    HALF_Y = 3
    LARGE_AXIS = 4
    LARGE = 5
    RADIUS = 6
    ROTATION = 7
    GOAL_SIDE = 8
    POSITION_X = 9
    POSITION_Y = 10
    FIXATE = 11
    LOWER_HALF = 12
    TARGET_KIND = 8
    TARGET = 9
    ANCHOR_X = 10
    ANCHOR_Y = 11
    TARGET_ANCHOR_X = 12
    TARGET_ANCHOR_Y = 13


NUM_DRAWS = 14


class JointDraw(enum.IntEnum):
    """Columns of the draws for a chosen attachment's joint parameters."""

    REVOLUTE = 0
    MOTOR_ON = 1
    BINDING = 2
    SPEED = 3
    POWER = 4
    LIMITS = 5
    LOWER = 6
    UPPER = 7


NUM_JOINT_DRAWS = len(JointDraw)


class ThrusterDraw(enum.IntEnum):
    """Columns of a thruster proposal's draws."""

    BODY = 0
    ANCHOR_X = 1
    ANCHOR_Y = 2
    SIGN = 3
    ALIGN = 4
    ANGLE = 5
    POWER = 6
    BINDING = 7


NUM_THRUSTER_DRAWS = len(ThrusterDraw)


@struct.dataclass
class Shape:
    """A proposed shape, before it has a slot."""

    is_polygon: jnp.ndarray  # () bool: rectangle, else disc
    half_extents: jnp.ndarray  # (2,) f32 [m] rectangle half sides (placement margin only for discs)
    radius: jnp.ndarray  # () f32 [m] disc radius
    position: jnp.ndarray  # (2,) f32 [m] centre of mass
    rotation: jnp.ndarray  # () f32 [rad]
    role: jnp.ndarray  # () i32 `Role`
    fixated: jnp.ndarray  # () bool: static shape


@struct.dataclass
class Attachment:
    """Where a proposed new shape (in `slot`) is jointed to an existing body."""

    slot: jnp.ndarray  # () i32 global index the new shape will take
    target: jnp.ndarray  # () i32 global index of the existing body
    anchor_new: jnp.ndarray  # (2,) f32 [m] joint point in the new shape's frame
    anchor_target: jnp.ndarray  # (2,) f32 [m] joint point in the target's frame
    both_polygons: jnp.ndarray  # () bool: rectangle-rectangle joint


@struct.dataclass
class JointSettings:
    """Type, motor and limits of an attachment's joint."""

    is_fixed: jnp.ndarray  # () bool
    motor_on: jnp.ndarray  # () bool
    motor_speed: jnp.ndarray  # () f32 [-]
    motor_power: jnp.ndarray  # () f32 [-]
    has_limits: jnp.ndarray  # () bool
    lower_angle: jnp.ndarray  # () f32 [rad]
    upper_angle: jnp.ndarray  # () f32 [rad]
    binding: jnp.ndarray  # () i32 motor action slot


# --------------------------------------------------------------------------- small helpers
def categorical(u, weights):
    """Index drawn with probability proportional to `weights` (>= 0) from one U[0, 1) draw; the last index if all 0."""
    cumulative = jnp.cumsum(weights)
    index = jnp.sum(cumulative <= u * cumulative[-1])
    return jnp.minimum(index, weights.shape[0] - 1).astype(jnp.int32)


def uniform_int(u, count: int):
    """Integer in [0, count) from one U[0, 1) draw."""
    return jnp.minimum(jnp.floor(u * count), count - 1).astype(jnp.int32)


def set_row(array, index, value):
    """`array` with row `index` replaced by `value` (a one-hot select, cheap under vmap)."""
    hit = jnp.arange(array.shape[0]) == index
    return jnp.where(hit.reshape((-1,) + (1,) * (array.ndim - 1)), jnp.asarray(value, array.dtype), array)


def rectangle_vertices(half_extents):
    """(4, 2) counter-clockwise corners of a rectangle centred at the origin."""
    hx, hy = half_extents[0], half_extents[1]
    return jnp.stack([jnp.stack([-hx, -hy]), jnp.stack([hx, -hy]), jnp.stack([hx, hy]), jnp.stack([-hx, hy])])


def body_half_extents(vertices):
    """(..., 2) half sides of the axis-aligned bounding box of body-frame vertices (..., 4, 2)."""
    return 0.5 * (jnp.max(vertices, axis=-2) - jnp.min(vertices, axis=-2))


def shape_mass(shape: Shape):
    """Mass [kg] and inertia about the centre [kg m^2] of a proposed shape at `SHAPE_DENSITY` (a disc's inertia by
    `DISC_INERTIA_SHARE`)."""
    polygon_mass, _, polygon_inertia = polygon_mass_properties(
        rectangle_vertices(shape.half_extents), MAX_POLYGON_VERTICES, SHAPE_DENSITY
    )
    circle_mass, _ = circle_mass_properties(shape.radius, SHAPE_DENSITY)
    circle_inertia = DISC_INERTIA_SHARE * circle_mass * shape.radius**2
    return (
        jnp.where(shape.is_polygon, polygon_mass, circle_mass),
        jnp.where(shape.is_polygon, polygon_inertia, circle_inertia),
    )


def role_counts(level: Level):
    """(4,) i32 number of active shapes of each role (boundaries included)."""
    roles = jnp.where(level.sim.bodies.active, level.task.roles, -1)
    return jnp.sum(roles[:, None] == jnp.arange(len(Role)), axis=0).astype(jnp.int32)


def sample_role(u, level: Level, allowed):
    """Green and blue first (whichever is missing), then default or red (red weight 1/3 while no red exists)."""
    counts = role_counts(level)
    needs_green, needs_blue = counts[Role.GREEN] == 0, counts[Role.BLUE] == 0
    goals_done = ~needs_green & ~needs_blue
    weights = jnp.stack([goals_done, needs_green, needs_blue, goals_done & (counts[Role.RED] == 0)]).astype(jnp.float32)
    weights = weights * jnp.asarray([1.0, 1.0, 1.0, RED_WEIGHT]) * allowed
    return categorical(u, weights)


def free_slots(level: Level, static: StaticEnvParams):
    """First free polygon slot, first free circle slot (global indices), and whether each exists."""
    active = level.sim.bodies.active
    reserved, p = static.sim.num_reserved_static, static.sim.num_polygons
    polygon_slot = reserved + jnp.argmin(active[reserved:p])
    circle_slot = p + jnp.argmin(active[p:])
    return polygon_slot, circle_slot, ~jnp.all(active[reserved:p]), ~jnp.all(active[p:])


def _shape_kind(u, space_polygon, space_circle):
    """True for a rectangle: 50/50 while both kinds have a free slot."""
    return categorical(u[Draw.KIND], jnp.stack([space_polygon, space_circle]).astype(jnp.float32)) == 0


def _shape_size(u, is_polygon):
    """Rectangle half extents (2,) (or the disc's placement half extents) and disc radius (0 for rectangles)."""
    base = jnp.where(
        is_polygon,
        MIN_HALF_EXTENT + jnp.stack([u[Draw.HALF_X], u[Draw.HALF_Y]]) * (MAX_HALF_EXTENT - MIN_HALF_EXTENT),
        MIN_HALF_EXTENT,
    )
    scale = jnp.where(u[Draw.LARGE] < LARGE_SIDE_CHANCE, LARGE_SIDE_SCALE, 1.0)
    half_extents = base * jnp.where(jnp.arange(2) == uniform_int(u[Draw.LARGE_AXIS], 2), scale, 1.0)
    radius = MIN_RADIUS + u[Draw.RADIUS] * (MAX_RADIUS - MIN_RADIUS)
    return half_extents, jnp.where(is_polygon, 0.0, radius)


# --------------------------------------------------------------------------- proposals
def propose_free_shape(u, level: Level, static: StaticEnvParams, no_fixate) -> Shape:
    """A shape placed anywhere in the arena (Kinetix `mutate_add_shape`)."""
    _, _, space_polygon, space_circle = free_slots(level, static)
    is_polygon = _shape_kind(u, space_polygon, space_circle)
    half_extents, radius = _shape_size(u, is_polygon)
    role = sample_role(u[Draw.ROLE], level, jnp.ones(len(Role)))
    margin = jnp.maximum(jnp.max(half_extents) * math.sqrt(2.0), radius)
    low = jnp.stack([margin, margin + FLOOR_TOP])
    high = jnp.full(2, ARENA_SIZE - margin)
    half = ARENA_SIZE / 2.0
    goal_side = u[Draw.GOAL_SIDE] < GOAL_SIDE_CHANCE
    low = low.at[0].add(jnp.where(goal_side & (role == Role.BLUE), half, 0.0))
    high = high.at[0].add(jnp.where(goal_side & (role == Role.GREEN), -half, 0.0))
    position = low + jnp.stack([u[Draw.POSITION_X], u[Draw.POSITION_Y]]) * (high - low)
    shape = Shape(
        is_polygon=is_polygon,
        half_extents=half_extents,
        radius=radius,
        position=position,
        rotation=u[Draw.ROTATION] * 2.0 * math.pi,
        role=role,
        fixated=jnp.zeros((), bool),
    )
    mass, _ = shape_mass(shape)
    fixated = (u[Draw.FIXATE] < jnp.minimum(1.0, FIXATE_CHANCE_MIN + FIXATE_CHANCE_PER_KG * mass)) & ~no_fixate
    lower_half_chance = jnp.where(role != Role.DEFAULT, FIXATED_GOAL_LOWER_HALF_CHANCE, 0.0)
    move_down = fixated & (u[Draw.LOWER_HALF] < lower_half_chance) & (position[1] >= half)
    return shape.replace(fixated=fixated, position=position.at[1].add(jnp.where(move_down, -half, 0.0)))


def joint_counts(level: Level):
    """(N,) i32 number of active joints at each body."""
    joints, n = level.sim.joints, level.sim.bodies.active.shape[0]
    ends = jnp.concatenate([joints.body_a, joints.body_b])
    active = jnp.concatenate([joints.active, joints.active])
    return jnp.sum((ends[:, None] == jnp.arange(n)) & active[:, None], axis=0).astype(jnp.int32)


def _random_point_in_box(ux, uy, half_extents):
    return (2.0 * jnp.stack([ux, uy]) - 1.0) * half_extents


def _sticks_out(small, big):
    """Kinetix's test that shape `small` of a jointed pair is not hidden inside shape `big`.

    Each argument is (is_polygon, half_extents, anchor, radius); a disc's anchor is its centre. A disc never
    sticks out of a disc.
    """
    small_is_polygon, small_extents, small_anchor, small_radius = small
    big_is_polygon, big_extents, big_anchor, big_radius = big
    big_inner = jnp.min(big_extents - jnp.abs(big_anchor))  # anchor to the nearest side of a rectangle
    small_far = jnp.linalg.norm(jnp.abs(small_anchor) + small_extents)  # anchor to the farthest corner
    big_reach = jnp.where(big_is_polygon, big_inner, big_radius)
    polygon_out = small_far > big_reach + VISIBILITY_MARGIN
    disc_out = big_is_polygon & (big_inner + VISIBILITY_MARGIN < small_radius)
    return jnp.where(small_is_polygon, polygon_out, disc_out)


def _connection_weights(level: Level, static: StaticEnvParams):
    """(N,) weight of each body as the target of a new joint (Kinetix's: fewer joints, more weight; a fixated body
    less), and (N,) which bodies are candidates (active, not reserved)."""
    bodies = level.sim.bodies
    n, p, reserved = static.num_bodies, static.sim.num_polygons, static.sim.num_reserved_static
    index = jnp.arange(n)
    is_polygon_slot = index < p
    candidate = bodies.active & (index >= reserved)
    connections = joint_counts(level)
    weight = jnp.where(bodies.is_static, CONNECT_TO_FIXATED_WEIGHT, 1.0) * jnp.where(
        is_polygon_slot,
        jnp.maximum(MAX_POLYGON_JOINTS - connections, 0) / MAX_POLYGON_JOINTS,
        (connections == 0).astype(jnp.float32),
    )
    return jnp.where(candidate, weight, 0.0), candidate


def _connection_target(u, level: Level, static: StaticEnvParams, space_polygon):
    """The body a new shape is jointed to, and whether it is a polygon: first its kind, then a body of that kind by
    `_connection_weights` (without a weighted one, any active body of that kind, boundaries included)."""
    is_polygon_slot = jnp.arange(static.num_bodies) < static.sim.num_polygons
    weight, candidate = _connection_weights(level, static)
    circle_weight = jnp.sum(jnp.where(is_polygon_slot, 0.0, weight))
    target_kind_weights = jnp.stack(
        [jnp.any(candidate & is_polygon_slot), jnp.any(candidate & ~is_polygon_slot) & (circle_weight > 0)]
    ).astype(jnp.float32)
    target_is_polygon = (categorical(u[Draw.TARGET_KIND], target_kind_weights) == 0) | ~space_polygon
    kind_mask = is_polygon_slot == target_is_polygon
    kind_weight = jnp.where(kind_mask, weight, 0.0)
    active = level.sim.bodies.active
    kind_weight = jnp.where(jnp.sum(kind_weight) > 0, kind_weight, (kind_mask & active).astype(jnp.float32))
    return categorical(u[Draw.TARGET], kind_weight), target_is_polygon


def _roles_next_to(target_role):
    """(4,) 1 for each role a shape jointed to a body of `target_role` may take: attached to green or blue, neither
    the opposite goal nor red; attached to red, no goal role."""
    return jnp.where(
        target_role == Role.DEFAULT,
        jnp.ones(len(Role)),
        jnp.where(
            target_role == Role.RED,
            jnp.asarray([1.0, 0.0, 0.0, 1.0]),
            jnp.ones(len(Role)).at[Role.GREEN + Role.BLUE - target_role].set(0.0).at[Role.RED].set(0.0),
        ),
    )


def propose_connected_shape(u, level: Level, static: StaticEnvParams):
    """A shape jointed to an existing one (Kinetix `mutate_add_connected_shape`): (Shape, Attachment, hidden).

    `hidden`: one shape of the pair would be hidden inside the other.
    """
    bodies = level.sim.bodies
    polygon_slot, circle_slot, space_polygon, space_circle = free_slots(level, static)
    target, target_is_polygon = _connection_target(u, level, static, space_polygon)

    # A disc target always gets a rectangle when one fits (no disc-disc joints).
    is_polygon = (_shape_kind(u, space_polygon, space_circle) | ~target_is_polygon) & space_polygon
    half_extents, radius = _shape_size(u, is_polygon)
    rotation = u[Draw.ROTATION] * 2.0 * math.pi
    anchor_new = jnp.where(
        is_polygon, _random_point_in_box(u[Draw.ANCHOR_X], u[Draw.ANCHOR_Y], half_extents), jnp.zeros(2)
    )
    target_extents = body_half_extents(bodies.vertices[target])
    anchor_target = jnp.where(
        target_is_polygon,
        _random_point_in_box(u[Draw.TARGET_ANCHOR_X], u[Draw.TARGET_ANCHOR_Y], target_extents),
        jnp.zeros(2),
    )
    joint_point = bodies.position[target] + rotate(bodies.rotation[target], anchor_target)
    position = joint_point - rotate(rotation, anchor_new)

    allowed = _roles_next_to(level.task.roles[target])
    shape = Shape(
        is_polygon=is_polygon,
        half_extents=half_extents,
        radius=radius,
        position=position,
        rotation=rotation,
        role=sample_role(u[Draw.ROLE], level, allowed),
        fixated=jnp.zeros((), bool),
    )

    attachment = Attachment(
        slot=jnp.where(is_polygon, polygon_slot, circle_slot).astype(jnp.int32),
        target=target,
        anchor_new=anchor_new,
        anchor_target=anchor_target,
        both_polygons=is_polygon & target_is_polygon,
    )
    new = (is_polygon, half_extents, anchor_new, radius)
    old = (target_is_polygon, target_extents, anchor_target, bodies.radius[target])
    hidden = ~(_sticks_out(new, old) & _sticks_out(old, new))
    return shape, attachment, hidden


def joint_settings(u, level: Level, attachment: Attachment, force_revolute) -> JointSettings:
    """Joint type (revolute until two exist, then 50/50 with fixed), motor and limits of a chosen attachment."""
    joints = level.sim.joints
    revolute_count = jnp.sum(joints.active & ~joints.is_fixed)
    is_revolute = (u[JointDraw.REVOLUTE] < REVOLUTE_CHANCE) | force_revolute | (revolute_count < MIN_REVOLUTE_JOINTS)
    power = jnp.where(
        attachment.both_polygons,
        MOTOR_POWER_RANGE[0] + u[JointDraw.POWER] * (MOTOR_POWER_RANGE[1] - MOTOR_POWER_RANGE[0]),
        WHEEL_MOTOR_POWER,
    )
    has_limits = is_revolute & attachment.both_polygons & (u[JointDraw.LIMITS] < JOINT_LIMIT_CHANCE)
    speed = MOTOR_SPEED_RANGE[0] + u[JointDraw.SPEED] * (MOTOR_SPEED_RANGE[1] - MOTOR_SPEED_RANGE[0])
    return JointSettings(
        is_fixed=~is_revolute,
        motor_on=is_revolute & (u[JointDraw.MOTOR_ON] < MOTOR_ON_CHANCE),
        motor_speed=jnp.where(is_revolute, speed, 0.0),
        motor_power=jnp.where(is_revolute, power, 0.0),
        has_limits=has_limits,
        lower_angle=jnp.where(has_limits, -u[JointDraw.LOWER] * JOINT_LIMIT_MAX, 0.0),
        upper_angle=jnp.where(has_limits, u[JointDraw.UPPER] * JOINT_LIMIT_MAX, 0.0),
        binding=uniform_int(u[JointDraw.BINDING], NUM_MOTOR_BINDINGS),
    )


# --------------------------------------------------------------------------- overlap score
def overlap_count(shape: Shape, level: Level, static: StaticEnvParams):
    """() i32 number of active shapes of `level` that the proposed shape overlaps (penetration > 0)."""
    bodies = level.sim.bodies
    extents = body_half_extents(bodies.vertices)  # (N, 2)
    dx, dy = bodies.position[:, 0] - shape.position[0], bodies.position[:, 1] - shape.position[1]
    c, s = jnp.cos(shape.rotation), jnp.sin(shape.rotation)
    cb, sb = jnp.cos(bodies.rotation), jnp.sin(bodies.rotation)
    # Old centres in the new shape's frame, and the new centre in each old body's frame.
    old_x, old_y = c * dx + s * dy, -s * dx + c * dy
    new_x, new_y = -(cb * dx + sb * dy), -(-sb * dx + cb * dy)
    # Rectangle against rectangle: separating axes of both (|cos|, |sin| of the relative angle couple the extents).
    cos_rel, sin_rel = jnp.abs(c * cb + s * sb), jnp.abs(s * cb - c * sb)
    hx, hy = shape.half_extents[0], shape.half_extents[1]
    ex, ey = extents[:, 0], extents[:, 1]
    box_box = (
        (jnp.abs(old_x) < hx + cos_rel * ex + sin_rel * ey)
        & (jnp.abs(old_y) < hy + sin_rel * ex + cos_rel * ey)
        & (jnp.abs(new_x) < ex + cos_rel * hx + sin_rel * hy)
        & (jnp.abs(new_y) < ey + sin_rel * hx + cos_rel * hy)
    )
    # Disc against rectangle (either one being the disc): distance from the centre to the clamped point.
    old_disc_in_new_box = (old_x - jnp.clip(old_x, -hx, hx)) ** 2 + (old_y - jnp.clip(old_y, -hy, hy)) ** 2 < (
        bodies.radius**2
    )
    new_disc_in_old_box = (new_x - jnp.clip(new_x, -ex, ex)) ** 2 + (new_y - jnp.clip(new_y, -ey, ey)) ** 2 < (
        shape.radius**2
    )
    disc_disc = dx**2 + dy**2 < (shape.radius + bodies.radius) ** 2
    old_is_polygon = jnp.arange(bodies.active.shape[0]) < static.sim.num_polygons
    overlap = jnp.where(
        shape.is_polygon,
        jnp.where(old_is_polygon, box_box, old_disc_in_new_box),
        jnp.where(old_is_polygon, new_disc_in_old_box, disc_disc),
    )
    collide = bodies.active & modes_collide(SHAPE_COLLISION_MODE, bodies.collision_mode)
    return jnp.sum(overlap & collide).astype(jnp.int32)


# --------------------------------------------------------------------------- writing into a level
def place_shape(level: Level, shape: Shape, slot) -> Level:
    """`level` with `shape` in body slot `slot` (nothing if out of range): at rest, density 1, friction 1."""
    mass, inertia = shape_mass(shape)
    b = level.sim.bodies
    vertices = jnp.where(shape.is_polygon, rectangle_vertices(shape.half_extents), 0.0)
    bodies = b.replace(
        position=set_row(b.position, slot, shape.position),
        rotation=set_row(b.rotation, slot, shape.rotation),
        velocity=set_row(b.velocity, slot, jnp.zeros(2)),
        angular_velocity=set_row(b.angular_velocity, slot, 0.0),
        inverse_mass=set_row(b.inverse_mass, slot, jnp.where(shape.fixated, 0.0, 1.0 / mass)),
        inverse_inertia=set_row(b.inverse_inertia, slot, jnp.where(shape.fixated, 0.0, 1.0 / inertia)),
        friction=set_row(b.friction, slot, SHAPE_FRICTION),
        restitution=set_row(b.restitution, slot, 0.0),
        collision_mode=set_row(b.collision_mode, slot, SHAPE_COLLISION_MODE),
        active=set_row(b.active, slot, True),
        n_vertices=set_row(b.n_vertices, slot, jnp.where(shape.is_polygon, MAX_POLYGON_VERTICES, 0)),
        vertices=set_row(b.vertices, slot, vertices),
        radius=set_row(b.radius, slot, shape.radius),
    )
    task = level.task.replace(
        roles=set_row(level.task.roles, slot, shape.role),
        densities=set_row(level.task.densities, slot, SHAPE_DENSITY),
    )
    return level.replace(sim=level.sim.replace(bodies=bodies), task=task)


def place_joint(level: Level, attachment: Attachment, settings: JointSettings, slot) -> Level:
    """`level` with a joint in slot `slot` (nothing if out of range) from the placed new shape to its target.

    The lower global index becomes body a. As in Kinetix, a fixed joint holds the current relative rotation, while a
    revolute joint's reference angle is 0, so its limits bound the absolute relative rotation (a sampled joint may
    start outside them and snap in at t = 0).
    """
    j, rotation = level.sim.joints, level.sim.bodies.rotation
    new_is_a = attachment.slot < attachment.target
    body_a = jnp.where(new_is_a, attachment.slot, attachment.target)
    body_b = jnp.where(new_is_a, attachment.target, attachment.slot)
    anchor_a = jnp.where(new_is_a, attachment.anchor_new, attachment.anchor_target)
    anchor_b = jnp.where(new_is_a, attachment.anchor_target, attachment.anchor_new)
    joints = j.replace(
        body_a=set_row(j.body_a, slot, body_a),
        body_b=set_row(j.body_b, slot, body_b),
        anchor_a=set_row(j.anchor_a, slot, anchor_a),
        anchor_b=set_row(j.anchor_b, slot, anchor_b),
        reference_angle=set_row(
            j.reference_angle, slot, jnp.where(settings.is_fixed, rotation[body_b] - rotation[body_a], 0.0)
        ),
        active=set_row(j.active, slot, True),
        is_fixed=set_row(j.is_fixed, slot, settings.is_fixed),
        motor_on=set_row(j.motor_on, slot, settings.motor_on),
        motor_speed=set_row(j.motor_speed, slot, settings.motor_speed),
        motor_power=set_row(j.motor_power, slot, settings.motor_power),
        has_limits=set_row(j.has_limits, slot, settings.has_limits),
        lower_angle=set_row(j.lower_angle, slot, settings.lower_angle),
        upper_angle=set_row(j.upper_angle, slot, settings.upper_angle),
    )
    task = level.task.replace(motor_bindings=set_row(level.task.motor_bindings, slot, settings.binding))
    return level.replace(sim=level.sim.replace(joints=joints), task=task)


def add_thruster(u, level: Level, static: StaticEnvParams, wanted=True) -> Level:
    """`level` with a thruster on a random movable shape, if `wanted`, a movable shape exists and a slot is free."""
    bodies, t = level.sim.bodies, level.sim.thrusters
    movable = bodies.active & ~bodies.is_static
    possible = wanted & jnp.any(movable) & ~jnp.all(t.active)
    body = categorical(u[ThrusterDraw.BODY], movable.astype(jnp.float32))
    is_polygon = body < static.sim.num_polygons
    in_box = _random_point_in_box(
        u[ThrusterDraw.ANCHOR_X], u[ThrusterDraw.ANCHOR_Y], body_half_extents(bodies.vertices[body])
    )
    angle = 2.0 * math.pi * u[ThrusterDraw.ANCHOR_Y]
    in_disc = u[ThrusterDraw.ANCHOR_X] * bodies.radius[body] * jnp.stack([jnp.cos(angle), jnp.sin(angle)])
    anchor = jnp.where(is_polygon, in_box, in_disc)
    direction = jnp.where(u[ThrusterDraw.SIGN] < 0.5, -1.0, 1.0) * anchor
    direction = jnp.where(jnp.all(direction == 0.0), jnp.asarray([1.0, 0.0]), direction)
    thrust_angle = jnp.where(
        u[ThrusterDraw.ALIGN] < THRUSTER_ALIGN_CHANCE,
        jnp.arctan2(direction[1], direction[0]),
        2.0 * math.pi * u[ThrusterDraw.ANGLE],
    )
    scale = THRUSTER_SCALE_RANGE[0] + u[ThrusterDraw.POWER] * (THRUSTER_SCALE_RANGE[1] - THRUSTER_SCALE_RANGE[0])
    power = THRUSTER_POWER_PER_KG * scale / jnp.where(movable[body], bodies.inverse_mass[body], 1.0)
    slot = jnp.where(possible, jnp.argmin(t.active), t.active.shape[0])  # out of range: nothing is written
    thrusters = t.replace(
        body=set_row(t.body, slot, body),
        anchor=set_row(t.anchor, slot, anchor),
        angle=set_row(t.angle, slot, thrust_angle),
        power=set_row(t.power, slot, power),
        active=set_row(t.active, slot, True),
    )
    bindings = set_row(level.task.thruster_bindings, slot, uniform_int(u[ThrusterDraw.BINDING], NUM_THRUSTER_BINDINGS))
    return level.replace(
        sim=level.sim.replace(thrusters=thrusters), task=level.task.replace(thruster_bindings=bindings)
    )
