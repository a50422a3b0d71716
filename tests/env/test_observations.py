"""Symbolic observations: Kinetix's shapes per size, hand-derived feature values, clipping, masking and batching."""

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from kforge.engine import SceneBuilder, pair_layout
from kforge.env import Role, StaticEnvParams, reset
from kforge.env.observations import EntityObservation, ObservationType, observation_shape, observe
from kforge.env.state import EnvState, Level, Task

S_STATIC = StaticEnvParams.for_size("s")
M_STATIC = StaticEnvParams.for_size("m")
NUM_BODIES_S = 7

observe_jit = jax.jit(observe, static_argnums=(1, 2))

# Hand-built scene (world coordinates): a green 0.4 x 0.2 m box of density 2 rotated by 0.3 rad, a blue disc of
# radius 0.25 m, a motorised revolute joint with limits between them, and a thruster on the box.
BOX_POSITION = (2.0, 1.5)
BOX_SIZE = (0.4, 0.2)
BOX_ROTATION = 0.3
BOX_DENSITY = 2.0
BOX_VELOCITY = (0.5, -1.0)
BOX_ANGULAR_VELOCITY = 3.0
BOX_FRICTION = 0.7
BOX_RESTITUTION = 0.2
DISC_POSITION = (3.0, 2.0)
DISC_RADIUS = 0.25
JOINT_POINT = (2.2, 1.5)
JOINT_LIMITS = (-0.5, 0.7)
MOTOR_SPEED = 1.5
MOTOR_POWER = 2.0
MOTOR_BINDING = 3
THRUSTER_POINT = (1.8, 1.5)
THRUSTER_WORLD_ANGLE = BOX_ROTATION + math.pi / 2
THRUSTER_POWER = 1.5
THRUSTER_BINDING = 1
GRAVITY_FEATURE = -0.981

SHAPE_WIDTH = {"polygon": 26, "circle": 18}
JOINT_WIDTH = 22
THRUSTER_WIDTH = 8


def build_scene(static: StaticEnvParams) -> tuple[EnvState, int, int]:
    """The hand-built scene at `static`'s size; returns the start state and the box's and disc's body indices."""
    builder = SceneBuilder(static.sim)
    box = builder.add_box(
        BOX_POSITION,
        BOX_SIZE,
        rotation=BOX_ROTATION,
        density=BOX_DENSITY,
        friction=BOX_FRICTION,
        restitution=BOX_RESTITUTION,
        velocity=BOX_VELOCITY,
        angular_velocity=BOX_ANGULAR_VELOCITY,
    )
    disc = builder.add_circle(DISC_POSITION, DISC_RADIUS)
    builder.add_revolute_joint(
        box, disc, JOINT_POINT, motor_on=True, motor_speed=MOTOR_SPEED, motor_power=MOTOR_POWER, limits=JOINT_LIMITS
    )
    builder.add_thruster(box, THRUSTER_POINT, THRUSTER_WORLD_ANGLE, THRUSTER_POWER)
    n, j, t = static.num_bodies, static.sim.num_joints, static.sim.num_thrusters
    roles = np.zeros(n, np.int32)
    roles[box], roles[disc] = Role.GREEN, Role.BLUE
    task = Task(
        roles=jnp.asarray(roles),
        densities=jnp.asarray(builder.densities, jnp.float32),
        motor_bindings=jnp.full((j,), MOTOR_BINDING, jnp.int32),
        thruster_bindings=jnp.full((t,), THRUSTER_BINDING, jnp.int32),
        motor_auto=jnp.zeros((j,), bool),
    )
    return reset(Level(sim=builder.build(), task=task)), box, disc


def body_frame(rotation: float, world_offset) -> np.ndarray:
    """A world offset expressed in a frame rotated by `rotation`."""
    c, s = math.cos(rotation), math.sin(rotation)
    x, y = world_offset
    return np.array([c * x + s * y, -s * x + c * y])


def expected_box_row() -> np.ndarray:
    """The 26 Kinetix polygon features of the green box, derived by hand."""
    width, height = BOX_SIZE
    mass = BOX_DENSITY * width * height
    inertia = mass * (width**2 + height**2) / 12
    half_w, half_h = width / 2, height / 2
    clockwise_from_top_left = [(-half_w, half_h), (half_w, half_h), (half_w, -half_h), (-half_w, -half_h)]
    return np.array(
        [*BOX_POSITION, *BOX_VELOCITY, 1 / mass, 1 / inertia, BOX_DENSITY, math.tanh(BOX_ANGULAR_VELOCITY / 10)]
        + [0, 1, 0, 0]
        + [math.sin(BOX_ROTATION), math.cos(BOX_ROTATION), BOX_FRICTION, BOX_RESTITUTION]
        + [0.0]
        + [coordinate for vertex in clockwise_from_top_left for coordinate in vertex]
        + [0.0]
    )


def expected_disc_row() -> np.ndarray:
    mass = math.pi * DISC_RADIUS**2
    inertia = mass * DISC_RADIUS**2 / 2
    return np.array(
        [*DISC_POSITION, 0, 0, 1 / mass, 1 / inertia, 1.0, 0.0] + [0, 0, 1, 0] + [0, 1, 1.0, 0.0] + [DISC_RADIUS, 1.0]
    )


def expected_joint_row(from_box: bool) -> np.ndarray:
    """The 22 joint features seen from the box (a) or from the disc (b)."""
    anchor_box = body_frame(BOX_ROTATION, np.subtract(JOINT_POINT, BOX_POSITION))
    anchor_disc = np.subtract(JOINT_POINT, DISC_POSITION)
    first, second = (anchor_box, anchor_disc) if from_box else (anchor_disc, anchor_box)
    reference = 0.0 - BOX_ROTATION
    lower, upper = JOINT_LIMITS
    binding = [0.0] * 4
    binding[MOTOR_BINDING] = 1.0
    return np.array(
        [1, 0, *first, *second, math.sin(reference), math.cos(reference), MOTOR_SPEED, MOTOR_POWER, 1, 1]
        + binding
        + [math.sin(lower), math.cos(lower), math.sin(upper), math.cos(upper), lower - reference, upper - reference]
    )


def expected_thruster_row() -> np.ndarray:
    anchor = body_frame(BOX_ROTATION, np.subtract(THRUSTER_POINT, BOX_POSITION))
    binding = [0.0, 0.0]
    binding[THRUSTER_BINDING] = 1.0
    body_angle = THRUSTER_WORLD_ANGLE - BOX_ROTATION
    return np.array([1, *anchor, *binding, math.sin(body_angle), math.cos(body_angle), THRUSTER_POWER])


def one_hot(index: int, size: int = NUM_BODIES_S) -> np.ndarray:
    return np.eye(size)[index]


# Offsets in the size-s flat vector: floor row, free polygon row, 2 circle rows, joint row, thruster row, gravity.
FLAT_BOX = slice(26, 52)
FLAT_CIRCLES = 52
FLAT_JOINT = FLAT_CIRCLES + 2 * 18
FLAT_THRUSTER = FLAT_JOINT + JOINT_WIDTH + 2 * NUM_BODIES_S


# --------------------------------------------------------------------------- shapes
SPEC_SHAPES = {
    "s": {"flat": (140,), "padded": (6, 41), "entity": ((5, 27), (2, 19), (2, 22), (1, 8), (4, 7, 7), (2, 2), (1,))},
    "m": {"flat": (247,), "padded": (10, 45), "entity": ((6, 27), (3, 19), (4, 22), (2, 8), (4, 9, 9), (4, 2), (2,))},
    "l": {
        "flat": (679,),
        "padded": (21, 59),
        "entity": ((12, 27), (4, 19), (12, 22), (2, 8), (4, 16, 16), (12, 2), (2,)),
    },
}


@pytest.mark.parametrize("size", ["s", "m", "l"])
def test_shapes_match_kinetix_table(size):
    static = StaticEnvParams.for_size(size)
    p, c, j, t = (static.sim.num_polygons, static.sim.num_circles, static.sim.num_joints, static.sim.num_thrusters)
    n = p + c
    expected = SPEC_SHAPES[size]
    assert expected["flat"] == ((p - 3) * 26 + c * 18 + j * (22 + 2 * n) + t * (8 + n) + 1,)

    flat = observation_shape(static, ObservationType.SYMBOLIC_FLAT)
    assert (flat.shape, flat.dtype) == (expected["flat"], jnp.float32)
    padded = observation_shape(static, ObservationType.SYMBOLIC_FLAT_PADDED)
    assert (padded.shape, padded.dtype) == (expected["padded"], jnp.float32)
    entity = observation_shape(static, ObservationType.SYMBOLIC_ENTITY)
    got = tuple(
        x.shape
        for x in (
            entity.polygons,
            entity.circles,
            entity.joints,
            entity.thrusters,
            entity.attention_mask,
            entity.joint_indexes,
            entity.thruster_indexes,
        )
    )
    assert got == expected["entity"]
    assert (entity.polygon_mask.shape, entity.joint_mask.shape) == ((p,), (2 * j,))
    pixels = observation_shape(static, ObservationType.PIXELS)
    assert (pixels.image.shape, pixels.image.dtype, pixels.global_info.shape) == ((125, 125, 3), jnp.float32, (1,))


def test_real_state_has_the_declared_shapes():
    state, _, _ = build_scene(S_STATIC)
    for observation_type in ObservationType:
        got = jax.tree.map(lambda x: (x.shape, x.dtype), observe_jit(state, S_STATIC, observation_type))
        declared = jax.tree.map(lambda x: (x.shape, x.dtype), observation_shape(S_STATIC, observation_type))
        assert got == declared, observation_type


def test_unknown_observation_type_is_rejected():
    state, _, _ = build_scene(S_STATIC)
    with pytest.raises(ValueError, match="unknown observation type"):
        observe(state, S_STATIC, "symbolic_flat")


# --------------------------------------------------------------------------- flat values
def test_flat_features_equal_hand_derived_values():
    state, box, disc = build_scene(S_STATIC)
    assert (box, disc) == (4, 5)
    obs = np.asarray(observe_jit(state, S_STATIC, ObservationType.SYMBOLIC_FLAT))

    floor = obs[:26]
    np.testing.assert_allclose(floor[:2], [2.5, 0.4 - 5.2], atol=1e-5)  # floor box 5 x 10.4 m, top at y = 0.4
    np.testing.assert_allclose(floor[4:6], [0.0, 0.0])  # static: infinite mass and inertia
    np.testing.assert_allclose(floor[8:12], [1, 0, 0, 0])  # DEFAULT role
    np.testing.assert_allclose(floor[17:25], [-2.5, 5.2, 2.5, 5.2, 2.5, -5.2, -2.5, -5.2], atol=1e-5)

    # Flat features are clipped to +-10: the inverse inertias (375 and 163 1/(kg m^2)) read 10.
    np.testing.assert_allclose(obs[FLAT_BOX], np.clip(expected_box_row(), -10, 10), rtol=1e-5, atol=1e-5)
    disc_row = np.clip(expected_disc_row(), -10, 10)
    np.testing.assert_allclose(obs[FLAT_CIRCLES : FLAT_CIRCLES + 18], disc_row, rtol=1e-5, atol=1e-5)
    np.testing.assert_array_equal(obs[FLAT_CIRCLES + 18 : FLAT_JOINT], 0.0)  # inactive circle slot

    joint = obs[FLAT_JOINT:FLAT_THRUSTER]
    np.testing.assert_allclose(joint[:JOINT_WIDTH], expected_joint_row(from_box=False), atol=1e-5)
    np.testing.assert_array_equal(joint[JOINT_WIDTH : JOINT_WIDTH + 7], one_hot(disc))  # "from" end: body b
    np.testing.assert_array_equal(joint[JOINT_WIDTH + 7 :], one_hot(box))

    thruster = obs[FLAT_THRUSTER:-1]
    np.testing.assert_allclose(thruster[:THRUSTER_WIDTH], expected_thruster_row(), atol=1e-5)
    np.testing.assert_array_equal(thruster[THRUSTER_WIDTH:], one_hot(box))
    assert obs[-1] == pytest.approx(GRAVITY_FEATURE)


def test_triangle_vertices_are_clockwise_with_unused_slot():
    builder = SceneBuilder(S_STATIC.sim)
    triangle = [(0.0, 0.0), (0.6, 0.0), (0.0, 0.3)]  # counter-clockwise, centroid (0.2, 0.1) from the first vertex
    builder.add_polygon((1.0, 1.0), triangle)
    n = S_STATIC.num_bodies
    task = Task(
        roles=jnp.zeros(n, jnp.int32),
        densities=jnp.ones(n),
        motor_bindings=jnp.zeros(1, jnp.int32),
        thruster_bindings=jnp.zeros(1, jnp.int32),
        motor_auto=jnp.zeros(1, bool),
    )
    obs = np.asarray(observe_jit(reset(Level(builder.build(), task)), S_STATIC, ObservationType.SYMBOLIC_FLAT))
    row = obs[FLAT_BOX]
    centroid = np.array([0.2, 0.1])
    clockwise = [np.subtract(v, centroid) for v in reversed(triangle)]
    np.testing.assert_allclose(row[17:23], np.concatenate(clockwise), atol=1e-5)
    np.testing.assert_array_equal(row[23:25], [-1.0, -1.0])
    assert row[25] == 1.0  # is triangle


def test_flat_values_are_clipped_and_nan_becomes_zero():
    state, box, _ = build_scene(S_STATIC)
    bodies = state.sim.bodies
    bodies = bodies.replace(
        velocity=bodies.velocity.at[box].set(jnp.array([25.0, -30.0])),
        position=bodies.position.at[box, 0].set(jnp.nan),
        angular_velocity=bodies.angular_velocity.at[box].set(jnp.nan),
    )
    obs = np.asarray(
        observe_jit(state.replace(sim=state.sim.replace(bodies=bodies)), S_STATIC, ObservationType.SYMBOLIC_FLAT)
    )
    box_row = obs[FLAT_BOX]
    np.testing.assert_array_equal(box_row[2:4], [10.0, -10.0])
    assert box_row[0] == 0.0 and box_row[7] == 0.0
    assert box_row[1] == pytest.approx(BOX_POSITION[1])
    assert np.all(np.isfinite(obs)) and np.all(np.abs(obs) <= 10.0)


def test_padded_rows_hold_flat_rows_type_and_gravity():
    state, _, _ = build_scene(S_STATIC)
    flat = np.asarray(observe_jit(state, S_STATIC, ObservationType.SYMBOLIC_FLAT))
    padded = np.asarray(observe_jit(state, S_STATIC, ObservationType.SYMBOLIC_FLAT_PADDED))
    width = JOINT_WIDTH + 2 * NUM_BODIES_S  # widest row: a joint with its endpoint one-hots
    np.testing.assert_array_equal(padded[1, :26], flat[FLAT_BOX])
    np.testing.assert_array_equal(padded[1, 26:width], 0.0)
    np.testing.assert_array_equal(padded[4, :width], flat[FLAT_JOINT:FLAT_THRUSTER])
    types = padded[:, width : width + 4]
    np.testing.assert_array_equal(types, np.eye(4)[[0, 0, 1, 1, 2, 3]])
    np.testing.assert_allclose(padded[:, -1], GRAVITY_FEATURE)


# --------------------------------------------------------------------------- entity values
def test_entity_rows_indexes_and_masks():
    state, box, disc = build_scene(S_STATIC)
    obs: EntityObservation = observe_jit(state, S_STATIC, ObservationType.SYMBOLIC_ENTITY)
    np.testing.assert_allclose(obs.polygons[box, :26], expected_box_row(), rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(obs.polygons[:, 26], [GRAVITY_FEATURE] * 5)
    np.testing.assert_allclose(obs.circles[0, :18], expected_disc_row(), rtol=1e-5, atol=1e-5)
    np.testing.assert_array_equal(obs.circles[1], 0.0)
    np.testing.assert_allclose(obs.joints[0], expected_joint_row(from_box=False), atol=1e-5)
    np.testing.assert_allclose(obs.joints[1], expected_joint_row(from_box=True), atol=1e-5)
    np.testing.assert_array_equal(obs.joint_indexes, [[disc, box], [box, disc]])
    np.testing.assert_allclose(obs.thrusters[0], expected_thruster_row(), atol=1e-5)
    np.testing.assert_array_equal(obs.thruster_indexes, [box])
    np.testing.assert_array_equal(obs.polygon_mask, [True] * 5)
    np.testing.assert_array_equal(obs.circle_mask, [True, False])
    np.testing.assert_array_equal(obs.joint_mask, [True, True])


def test_entity_attention_channels():
    state, box, disc = build_scene(S_STATIC)
    layout = pair_layout(S_STATIC.sim)
    pairs = list(zip(layout.body_a.tolist(), layout.body_b.tolist(), strict=True))
    feature = np.full((len(pairs), 2), -1, np.int32)
    feature[pairs.index((box, disc)), 1] = 3  # box-disc contact (second point slot)
    feature[pairs.index((0, box)), 0] = 5  # floor-box contact
    feature[pairs.index((0, 6)), 0] = 9  # floor and the inactive circle slot: ignored
    state = state.replace(sim=state.sim.replace(contacts=state.sim.contacts.replace(feature=jnp.asarray(feature))))
    mask = np.asarray(observe_jit(state, S_STATIC, ObservationType.SYMBOLIC_ENTITY).attention_mask)

    active = np.array([1, 1, 1, 1, 1, 1, 0], bool)
    np.testing.assert_array_equal(mask[0], np.outer(active, active))
    connected = np.diag(active)
    connected[box, disc] = connected[disc, box] = True
    np.testing.assert_array_equal(mask[1], connected)
    one_hop = np.zeros((7, 7), bool)
    one_hop[box, disc] = one_hop[disc, box] = True
    np.testing.assert_array_equal(mask[2], one_hop)
    contact = np.zeros((7, 7), bool)
    contact[disc, box] = True  # polygon-circle pairs sit at (circle, polygon), as in Kinetix
    contact[0, box] = True  # polygon pairs at (lower, higher)
    np.testing.assert_array_equal(mask[3], contact)


# --------------------------------------------------------------------------- purity and batching
def put_garbage_in_inactive_slots(state: EnvState, static: StaticEnvParams) -> EnvState:
    """Every field of every inactive body, joint and thruster slot overwritten with arbitrary values."""
    sim = state.sim

    def scramble(tree, active):
        def leaf(x):
            inactive = ~np.asarray(active).reshape(active.shape + (1,) * (x.ndim - 1))
            junk = jnp.full(x.shape, 3, x.dtype) if x.dtype != bool else jnp.ones(x.shape, bool)
            return jnp.where(inactive, junk, x)

        return jax.tree.map(leaf, tree)

    bodies = scramble(sim.bodies, sim.bodies.active).replace(active=sim.bodies.active)
    joints = scramble(sim.joints, sim.joints.active).replace(active=sim.joints.active)
    thrusters = scramble(sim.thrusters, sim.thrusters.active).replace(active=sim.thrusters.active)
    task = state.task.replace(
        roles=jnp.where(sim.bodies.active, state.task.roles, Role.RED),
        densities=jnp.where(sim.bodies.active, state.task.densities, 7.0),
        motor_bindings=jnp.where(sim.joints.active, state.task.motor_bindings, 2),
        thruster_bindings=jnp.where(sim.thrusters.active, state.task.thruster_bindings, 0),
    )
    layout = pair_layout(static.sim)
    inactive_pair = ~(sim.bodies.active[layout.body_a] & sim.bodies.active[layout.body_b])
    contacts = sim.contacts.replace(feature=jnp.where(inactive_pair[:, None], 11, sim.contacts.feature))
    sim = sim.replace(bodies=bodies, joints=joints, thrusters=thrusters, contacts=contacts)
    return state.replace(sim=sim, task=task)


@pytest.mark.parametrize("observation_type", list(ObservationType))
def test_inactive_slots_do_not_change_the_observation(observation_type):
    state, _, _ = build_scene(M_STATIC)  # size m: one joint, one thruster and several body slots stay inactive
    assert not bool(state.sim.joints.active[1]) and not bool(state.sim.thrusters.active[1])
    garbage = put_garbage_in_inactive_slots(state, M_STATIC)
    assert not np.array_equal(np.asarray(garbage.sim.bodies.position), np.asarray(state.sim.bodies.position))
    first = observe_jit(state, M_STATIC, observation_type)
    again = observe_jit(state, M_STATIC, observation_type)
    with_garbage = observe_jit(garbage, M_STATIC, observation_type)
    jax.tree.map(np.testing.assert_array_equal, first, again)
    jax.tree.map(np.testing.assert_array_equal, first, with_garbage)


@pytest.mark.parametrize("observation_type", list(ObservationType))
def test_vmap_equals_per_item(observation_type):
    state, box, _ = build_scene(S_STATIC)
    shifts = jnp.array([0.0, 0.7, 1.9])

    def moved(shift):
        bodies = state.sim.bodies
        bodies = bodies.replace(
            position=bodies.position.at[box].add(jnp.array([shift, shift / 2])),
            rotation=bodies.rotation.at[box].add(shift),
        )
        return state.replace(sim=state.sim.replace(bodies=bodies))

    batch = jax.vmap(moved)(shifts)
    batched = jax.jit(jax.vmap(functools.partial(observe, static=S_STATIC, observation_type=observation_type)))(batch)
    for index, shift in enumerate(np.asarray(shifts)):
        single = observe_jit(moved(float(shift)), S_STATIC, observation_type)
        jax.tree.map(lambda b, s, i=index: np.testing.assert_allclose(b[i], s, atol=1e-6), batched, single)
    first, last = (jax.tree.leaves(jax.tree.map(lambda x, i=i: x[i], batched)) for i in (0, 2))
    assert any(not np.array_equal(a, b) for a, b in zip(first, last, strict=True))
