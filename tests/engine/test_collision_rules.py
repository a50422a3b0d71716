"""Which points overlapping shapes touch at and which impulses they start from
(`StaticSimParams.collision_rules`): Box2D's rules (the default) and Jax2D's, the latter's manifolds checked against
Jax2D's own narrowphase functions on random overlapping pairs (docs/physics.md).

Every test prints a `MEASURED` line (run pytest with -s to see them).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from engine_test_helpers import SIZE_M, SIZE_S, pair_index
from jax2d.collision import generate_manifold_circle_polygon, generate_manifolds_polygon_polygon
from jax2d.sim_state import CollisionManifold, RigidBody

from kforge.engine import NO_FEATURE, CollisionRules, SceneBuilder, pair_layout
from kforge.engine.collision import WorldGeometry, manifolds, polygon_circle, polygon_polygon, world_geometry
from kforge.engine.physics_step import match_warm_start
from kforge.engine.state import ContactCache
from tests.helpers import measured

PAIRS = 600
"""Random pairs drawn per comparison; about half of them overlap."""
POSITION_TOLERANCE = 1e-4
"""[m] float32 rounding of two ways of computing the same point."""
CIRCLE_VERTICES = np.array([[0.0, 1.0], [-1.0, -1.0], [1.0, -1.0]])
"""[m] the vertex array a Jax2D circle carries; its narrowphase reads only the radius."""
NORMAL_TOLERANCE = 1e-3
"""[-] a corner's normal from a centre close to it loses digits in both engines."""


def _random_shape(rng) -> np.ndarray:
    """Counter-clockwise local vertices of a box (half sides 5 cm-1 m) or, one time in three, a triangle."""
    if rng.uniform() < 1 / 3:
        while True:
            triangle = rng.uniform(-1.0, 1.0, (3, 2)) * rng.uniform(0.1, 1.0)
            area = np.cross(np.append(triangle[1] - triangle[0], 0.0), np.append(triangle[2] - triangle[0], 0.0))[2]
            if abs(area) > 0.02:
                triangle = triangle - triangle.mean(0)
                return triangle if area > 0 else triangle[::-1]
    half_width, half_height = rng.uniform(0.05, 1.0, 2)
    return np.array(
        [[-half_width, -half_height], [half_width, -half_height], [half_width, half_height], [-half_width, half_height]]
    )


def _rotation(angle):
    cos, sin = math.cos(angle), math.sin(angle)
    return np.array([[cos, -sin], [sin, cos]])


def _ours(local: np.ndarray, position, angle) -> WorldGeometry:
    """Our world geometry of one polygon (triangles repeat their first vertex, as `world_geometry` does)."""
    world = local @ _rotation(angle).T + position
    count = len(world)
    world = np.concatenate([world, world[:1]]) if count == 3 else world
    next_vertex = np.array([1, 2, 0, 0]) if count == 3 else np.array([1, 2, 3, 0])
    edge = world[next_vertex] - world
    normals = np.stack([edge[:, 1], -edge[:, 0]], -1) / np.linalg.norm(edge, axis=-1, keepdims=True).clip(1e-9)
    return WorldGeometry(world, normals, np.arange(4) < count, next_vertex, np.asarray(position), np.float32(0.0))


def _jax2d(local: np.ndarray, position, angle, radius=0.0) -> RigidBody:
    """Jax2D's body: clockwise local vertices."""
    clockwise = local[::-1]
    vertices = np.concatenate([clockwise, clockwise[:1]]) if len(local) == 3 else clockwise
    return RigidBody(
        position=np.asarray(position, np.float32),
        rotation=np.float32(angle),
        velocity=np.zeros(2, np.float32),
        angular_velocity=np.float32(0.0),
        inverse_mass=np.float32(1.0),
        inverse_inertia=np.float32(1.0),
        friction=np.float32(1.0),
        restitution=np.float32(0.0),
        collision_mode=np.int32(1),
        active=np.bool_(True),
        n_vertices=np.int32(len(local)),
        vertices=vertices.astype(np.float32),
        radius=np.float32(radius),
    )


def _stack(items):
    return jax.tree_util.tree_map(
        lambda *x: jnp.asarray(np.stack(x), jnp.float32 if x[0].dtype.kind == "f" else None), *items
    )


def _no_warm_start(points: int) -> CollisionManifold:
    zeros = np.zeros((points,), np.float32)
    return CollisionManifold(
        normal=np.zeros((points, 2), np.float32),
        penetration=zeros,
        collision_point=np.zeros((points, 2), np.float32),
        active=np.zeros((points,), bool),
        acc_impulse_normal=zeros,
        acc_impulse_tangent=zeros,
        restitution_velocity_target=zeros,
    )


def test_two_polygons_touch_at_jax2ds_points_under_its_rules():
    """Random boxes and triangles at random angles, the second at a random offset: wherever Jax2D finds them
    overlapping, ours under Jax2D's rules and placement has the same normal, the same points and each point's depth
    the pair's deepest overlap, Jax2D's penetration; where Jax2D finds none, neither does ours."""
    rng = np.random.default_rng(7)
    ours, theirs = [], []
    for _ in range(PAIRS):
        shape_a, shape_b = _random_shape(rng), _random_shape(rng)
        angle_a, angle_b = rng.uniform(-math.pi, math.pi, 2)
        offset = rng.uniform(-1.5, 1.5, 2)
        ours.append((_ours(shape_a, (0.0, 0.0), angle_a), _ours(shape_b, offset, angle_b)))
        theirs.append((_jax2d(shape_a, (0.0, 0.0), angle_a), _jax2d(shape_b, offset, angle_b)))
    a, b = (_stack([pair[i] for pair in ours]) for i in (0, 1))
    normal, point, separation, valid, _ = jax.vmap(polygon_polygon, in_axes=(0, 0, None, None, None))(
        a, b, jnp.float32(0.0), True, True
    )
    jax2d_a, jax2d_b = (_stack([pair[i] for pair in theirs]) for i in (0, 1))
    found = jax.vmap(generate_manifolds_polygon_polygon, in_axes=(0, 0, None))(jax2d_a, jax2d_b, _no_warm_start(2))
    normal, point, separation, valid = (np.asarray(x) for x in (normal, point, separation, valid))
    active, penetration = np.asarray(found.active), np.asarray(found.penetration)
    overlapping = active.any(1)
    two_points = int((active.sum(1) == 2).sum())
    measured("polygon pairs", drawn=PAIRS, overlapping=int(overlapping.sum()), with_two_points=two_points)
    assert overlapping.sum() > PAIRS // 4 and 0 < two_points < overlapping.sum()  # both kinds of manifold drawn
    np.testing.assert_array_equal(valid.sum(1), active.sum(1))
    for k in np.flatnonzero(overlapping):
        np.testing.assert_allclose(normal[k], np.asarray(found.normal)[k, 0], atol=NORMAL_TOLERANCE)
        ours_points = sorted(map(tuple, point[k][valid[k]]))
        jax2d_points = sorted(map(tuple, np.asarray(found.collision_point)[k][active[k]]))
        np.testing.assert_allclose(ours_points, jax2d_points, atol=POSITION_TOLERANCE)
        np.testing.assert_allclose(separation[k][valid[k]], -penetration[k][active[k]], atol=POSITION_TOLERANCE)


def test_a_polygon_and_a_circle_touch_at_jax2ds_point_under_its_rules():
    """Random boxes and triangles and circles (radius 5-60 cm) at random offsets, engulfed centres included: ours
    under Jax2D's rules and placement has Jax2D's normal, point and depth (a circle whose centre is inside counts its
    radius); under Box2D's rules an engulfed circle counts its radius plus its centre's depth."""
    rng = np.random.default_rng(11)
    polygons, circles, jax2d_polygons, jax2d_circles = [], [], [], []
    for _ in range(PAIRS):
        shape, angle = _random_shape(rng), rng.uniform(-math.pi, math.pi)
        radius, centre = rng.uniform(0.05, 0.6), rng.uniform(-1.5, 1.5, 2)
        polygons.append(_ours(shape, (0.0, 0.0), angle))
        circles.append(
            WorldGeometry(
                np.zeros((4, 2)), np.zeros((4, 2)), np.zeros(4, bool), np.zeros(4, np.int32), centre, np.float32(radius)
            )
        )
        jax2d_polygons.append(_jax2d(shape, (0.0, 0.0), angle))
        jax2d_circles.append(_jax2d(CIRCLE_VERTICES, centre, 0.0, radius))
    a, b = _stack(polygons), _stack(circles)
    play = jax.vmap(polygon_circle, in_axes=(0, 0, None, None, None))
    normal, point, separation, valid, _ = (np.asarray(x) for x in play(a, b, jnp.float32(0.0), True, True))
    box2d_separation = np.asarray(play(a, b, jnp.float32(0.0), True, False)[2])
    found = jax.vmap(generate_manifold_circle_polygon, in_axes=(0, 0, None))(
        _stack(jax2d_circles), _stack(jax2d_polygons), jax.tree_util.tree_map(lambda x: x[0], _no_warm_start(1))
    )
    active = np.asarray(found.active)
    radius = np.asarray(b.radius)
    engulfed = active & (np.asarray(found.penetration) == radius)
    measured("polygon-circle pairs", drawn=PAIRS, overlapping=int(active.sum()), engulfed=int(engulfed.sum()))
    assert active.sum() > PAIRS // 8 and engulfed.sum() > 10
    np.testing.assert_array_equal(valid[:, 0], active)
    np.testing.assert_allclose(
        normal[active], -np.asarray(found.normal)[active], atol=NORMAL_TOLERANCE
    )  # Jax2D's: circle to polygon
    np.testing.assert_allclose(point[active, 0], np.asarray(found.collision_point)[active], atol=POSITION_TOLERANCE)
    np.testing.assert_allclose(separation[active, 0], -np.asarray(found.penetration)[active], atol=POSITION_TOLERANCE)
    assert np.all(box2d_separation[engulfed, 0] < -radius[engulfed])


def _box_on_a_ledge(rules: CollisionRules):
    """A 50 x 20 cm box tilted up by 10 degrees, its lower left corner 3 cm into a fixed ledge's top and 5 cm short
    of the ledge's right end; its lower edge leaves the ledge's top before the end and passes the end 2.1 cm deep."""
    tilt = math.radians(10.0)
    corner = np.array([-0.05, -0.03])  # relative to the ledge's top right corner
    ledge_corner = np.array([2.5, 1.5])
    half = np.array([0.25, 0.1])
    centre = ledge_corner + corner + _rotation(tilt) @ half
    builder = SceneBuilder(SIZE_M)
    ledge = builder.add_box(ledge_corner + np.array([-0.2, -0.05]), (0.4, 0.1), static=True)
    box = builder.add_box(tuple(centre), tuple(2 * half), rotation=tilt)
    state = builder.build()
    layout = pair_layout(SIZE_M)
    found = manifolds(
        world_geometry(state.bodies), layout, jnp.zeros(layout.body_a.shape), True, rules == CollisionRules.JAX2D
    )
    k = pair_index(SIZE_M, ledge, box)
    point, separation = (np.asarray(x[k], np.float64) for x in (found.point, found.separation))
    return point - ledge_corner, separation, np.asarray(found.valid[k])


def test_a_box_past_a_ledges_end_keeps_a_point_at_the_end_under_box2ds_rules_and_none_under_jax2ds():
    """Box2D clips the box's lower edge to the ledge's top: a second point at the end, where the edge is
    3 - 5 tan(10 deg) = 2.12 cm deep. Jax2D moves the edge's far vertex (0.5 m along it, 5.7 cm above the top) back
    to the end, where it stays above the top: one point, at the corner."""
    end_depth = 0.03 - 0.05 * math.tan(math.radians(10.0))
    box2d_point, box2d_separation, box2d_valid = _box_on_a_ledge(CollisionRules.BOX2D)
    jax2d_point, jax2d_separation, jax2d_valid = _box_on_a_ledge(CollisionRules.JAX2D)
    measured("box past a ledge's end", box2d_points=box2d_point[box2d_valid], jax2d_points=jax2d_point[jax2d_valid])
    assert box2d_valid.all() and jax2d_valid.sum() == 1
    np.testing.assert_allclose(sorted(box2d_point[:, 0]), [-0.05, 0.0], atol=1e-5)
    np.testing.assert_allclose(sorted(box2d_point[:, 1]), [-0.03, -end_depth], atol=1e-5)
    np.testing.assert_allclose(jax2d_point[jax2d_valid][0], [-0.05, -0.03], atol=1e-5)
    np.testing.assert_allclose(jax2d_separation[jax2d_valid], [-0.03], atol=1e-5)


@pytest.mark.parametrize("rules", list(CollisionRules))
def test_an_engulfed_circle_counts_the_depth_its_rules_give(rules):
    """A circle of radius 10 cm centred 5 cm below a fixed box's top: 15 cm of overlap under Box2D's rules, its
    radius under Jax2D's."""
    builder = SceneBuilder(SIZE_S)
    block = builder.add_box((2.5, 1.0), (1.0, 0.5), static=True)
    circle = builder.add_circle((2.5, 1.2), 0.1)
    state = builder.build()
    layout = pair_layout(SIZE_S)
    found = manifolds(
        world_geometry(state.bodies), layout, jnp.zeros(layout.body_a.shape), True, rules == CollisionRules.JAX2D
    )
    k = pair_index(SIZE_S, block, circle)
    expected = {CollisionRules.BOX2D: -0.15, CollisionRules.JAX2D: -0.1}[rules]
    measured("engulfed circle", rules=rules.name, separation=float(found.separation[k, 0]))
    assert bool(found.valid[k, 0])
    assert float(found.separation[k, 0]) == pytest.approx(expected, abs=1e-5)


@pytest.mark.parametrize("rules", list(CollisionRules))
def test_a_point_starts_from_the_impulse_its_rules_match(rules):
    """Last step a pair touched at features 5 and 9 with normal impulses 1 and 2 N s; now at features 9 and 7.
    Box2D's rules match by feature: the first point (9) takes 2, the second (new) none. Jax2D's match by slot: 1 and
    2. A slot empty last step gives nothing under both."""
    cache = ContactCache(
        normal_impulse=jnp.array([[1.0, 2.0], [3.0, 4.0]]),
        tangent_impulse=jnp.array([[0.1, 0.2], [0.3, 0.4]]),
        feature=jnp.array([[5, 9], [6, NO_FEATURE]]),
    )
    feature = jnp.array([[9, 7], [6, 8]])
    normal, tangent = match_warm_start(cache, feature, rules == CollisionRules.JAX2D)
    expected = {CollisionRules.BOX2D: [[2.0, 0.0], [3.0, 0.0]], CollisionRules.JAX2D: [[1.0, 2.0], [3.0, 0.0]]}[rules]
    np.testing.assert_allclose(normal, expected)
    np.testing.assert_allclose(tangent, 0.1 * np.asarray(expected))
