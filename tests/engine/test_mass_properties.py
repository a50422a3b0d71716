"""Test group A: mass, centroid and inertia of shapes (rtol 1e-5), against closed-form formulas."""

from __future__ import annotations

import numpy as np
import pytest

from kforge.engine import SceneBuilder, StaticSimParams
from kforge.engine.geometry import circle_mass_properties, polygon_mass_properties

pytestmark = pytest.mark.smoke

RTOL = 1e-5
STATIC = StaticSimParams(num_polygons=8, num_circles=3, num_joints=1, num_thrusters=1)


def _builder(boundaries=False):
    return SceneBuilder(STATIC, boundaries=boundaries)


def _read_back(state, index):
    b = state.bodies
    return 1.0 / float(b.inverse_mass[index]), 1.0 / float(b.inverse_inertia[index])


def _padded(vertices):
    out = np.zeros((4, 2), np.float32)
    out[: len(vertices)] = vertices
    return out


def _signed_area(vertices):
    v = np.asarray(vertices, np.float64)
    w = np.roll(v, -1, 0)
    return 0.5 * np.sum(v[:, 0] * w[:, 1] - v[:, 1] * w[:, 0])


# --------------------------------------------------------------------------- boxes
@pytest.mark.parametrize("width,height,density", [(1.0, 1.0, 1.0), (0.7, 0.3, 2.5), (3.0, 0.05, 0.4)])
def test_box_mass_and_inertia_in_scene(width, height, density):
    builder = _builder()
    index = builder.add_box((1.3, 2.1), (width, height), rotation=0.4, density=density)
    mass, inertia = _read_back(builder.build(), index)
    expected_mass = density * width * height
    np.testing.assert_allclose(mass, expected_mass, rtol=RTOL)
    np.testing.assert_allclose(inertia, expected_mass * (width**2 + height**2) / 12.0, rtol=RTOL)


def test_box_mass_properties_function():
    width, height, density = 0.8, 0.45, 1.7
    vertices = np.array(
        [[-width / 2, -height / 2], [width / 2, -height / 2], [width / 2, height / 2], [-width / 2, height / 2]]
    )
    # Offset the box from the origin: the centroid and the inertia about it must follow.
    offset = np.array([0.3, -1.2])
    mass, centroid, inertia = polygon_mass_properties(_padded(vertices + offset), 4, density)
    expected_mass = density * width * height
    np.testing.assert_allclose(float(mass), expected_mass, rtol=RTOL)
    np.testing.assert_allclose(np.asarray(centroid), offset, rtol=RTOL, atol=1e-6)
    np.testing.assert_allclose(float(inertia), expected_mass * (width**2 + height**2) / 12.0, rtol=RTOL)


def test_box_stored_pose_and_vertices():
    builder = _builder()
    index = builder.add_box((1.5, 2.5), (0.6, 0.2), rotation=0.3)
    b = builder.build().bodies
    np.testing.assert_allclose(np.asarray(b.position[index]), [1.5, 2.5], rtol=RTOL)
    np.testing.assert_allclose(float(b.rotation[index]), 0.3, rtol=RTOL)
    assert int(b.n_vertices[index]) == 4
    verts = np.asarray(b.vertices[index], np.float64)
    expected = np.array([[-0.3, -0.1], [0.3, -0.1], [0.3, 0.1], [-0.3, 0.1]])
    np.testing.assert_allclose(verts, expected, rtol=RTOL, atol=1e-7)


# --------------------------------------------------------------------------- triangles (Jax2D bug B3)
TRIANGLES = [
    np.array([[0.0, 0.0], [1.2, 0.0], [0.3, 0.9]]),
    np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]),
    np.array([[-0.2, 0.1], [0.5, -0.3], [0.4, 0.6]]),
]


def _triangle_expected(vertices, density):
    a, b, c = np.linalg.norm(np.roll(vertices, -1, 0) - vertices, axis=1)
    mass = density * abs(_signed_area(vertices))
    return mass, vertices.mean(axis=0), mass * (a**2 + b**2 + c**2) / 36.0


@pytest.mark.parametrize("vertices", TRIANGLES)
def test_triangle_inertia_about_centroid(vertices):
    density = 1.3
    mass, centroid, inertia = _triangle_expected(vertices, density)
    builder = _builder()
    index = builder.add_polygon((2.0, 2.0), vertices, density=density)
    state = builder.build()
    got_mass, got_inertia = _read_back(state, index)
    np.testing.assert_allclose(got_mass, mass, rtol=RTOL)
    np.testing.assert_allclose(got_inertia, inertia, rtol=RTOL)
    np.testing.assert_allclose(np.asarray(state.bodies.position[index]), np.array([2.0, 2.0]) + centroid, rtol=RTOL)
    assert int(state.bodies.n_vertices[index]) == 3

    f_mass, f_centroid, f_inertia = polygon_mass_properties(_padded(vertices), 3, density)
    np.testing.assert_allclose(float(f_mass), mass, rtol=RTOL)
    np.testing.assert_allclose(np.asarray(f_centroid), centroid, rtol=RTOL, atol=1e-6)
    np.testing.assert_allclose(float(f_inertia), inertia, rtol=RTOL)


# --------------------------------------------------------------------------- trapezoid (Jax2D bug B4)
def _right_trapezoid_expected(density):
    """Vertices (0,0),(3,0),(2,1),(0,1): a 2x1 rectangle plus the triangle (2,0),(3,0),(2,1)."""
    rect_m, rect_c = density * 2.0, np.array([1.0, 0.5])
    rect_i = rect_m * (2.0**2 + 1.0**2) / 12.0
    tri = np.array([[2.0, 0.0], [3.0, 0.0], [2.0, 1.0]])
    tri_m, tri_c, tri_i = _triangle_expected(tri, density)
    mass = rect_m + tri_m
    centroid = (rect_m * rect_c + tri_m * tri_c) / mass
    inertia = rect_i + rect_m * np.sum((rect_c - centroid) ** 2) + tri_i + tri_m * np.sum((tri_c - centroid) ** 2)
    return mass, centroid, inertia


TRAPEZOID = np.array([[0.0, 0.0], [3.0, 0.0], [2.0, 1.0], [0.0, 1.0]]) * 0.4  # scaled to fit the arena
TRAPEZOID_SCALE = 0.4


def test_trapezoid_area_centroid_not_vertex_average():
    density = 2.0
    mass, centroid, inertia = _right_trapezoid_expected(density)
    s = TRAPEZOID_SCALE
    mass, centroid, inertia = mass * s**2, centroid * s, inertia * s**4
    # The vertex average differs from the area centroid by several cm: the test can tell them apart.
    assert np.linalg.norm(TRAPEZOID.mean(axis=0) - centroid) > 0.01

    position, rotation = np.array([1.0, 2.0]), 0.3
    builder = _builder()
    index = builder.add_polygon(position, TRAPEZOID, rotation=rotation, density=density)
    state = builder.build()
    b = state.bodies
    expected_position = position + np.array(
        [
            np.cos(rotation) * centroid[0] - np.sin(rotation) * centroid[1],
            np.sin(rotation) * centroid[0] + np.cos(rotation) * centroid[1],
        ]
    )
    np.testing.assert_allclose(np.asarray(b.position[index]), expected_position, rtol=RTOL)
    np.testing.assert_allclose(float(b.rotation[index]), rotation, rtol=RTOL)
    np.testing.assert_allclose(np.asarray(b.vertices[index], np.float64), TRAPEZOID - centroid, rtol=RTOL, atol=1e-6)
    got_mass, got_inertia = _read_back(state, index)
    np.testing.assert_allclose(got_mass, mass, rtol=RTOL)
    np.testing.assert_allclose(got_inertia, inertia, rtol=RTOL)

    f_mass, f_centroid, f_inertia = polygon_mass_properties(_padded(TRAPEZOID), 4, density)
    np.testing.assert_allclose(float(f_mass), mass, rtol=RTOL)
    np.testing.assert_allclose(np.asarray(f_centroid), centroid, rtol=RTOL)
    np.testing.assert_allclose(float(f_inertia), inertia, rtol=RTOL)


def test_symmetric_trapezoid_centroid_height():
    """Isosceles trapezoid, bases b1 (bottom) and b2 (top), height h: centroid height h (b1 + 2 b2) / (3 (b1 + b2))."""
    b1, b2, h = 2.0, 1.0, 1.0
    vertices = np.array([[-b1 / 2, 0.0], [b1 / 2, 0.0], [b2 / 2, h], [-b2 / 2, h]])
    builder = _builder()
    index = builder.add_polygon((2.5, 2.0), vertices)
    position = np.asarray(builder.build().bodies.position[index])
    np.testing.assert_allclose(position, [2.5, 2.0 + h * (b1 + 2 * b2) / (3 * (b1 + b2))], rtol=RTOL)


# --------------------------------------------------------------------------- discs (Jax2D bug B2)
@pytest.mark.parametrize("radius,density", [(0.5, 1.0), (0.1, 3.0), (0.37, 0.6)])
def test_disc_mass_and_inertia(radius, density):
    expected_mass = density * np.pi * radius**2
    expected_inertia = 0.5 * expected_mass * radius**2
    builder = _builder()
    index = builder.add_circle((2.0, 3.0), radius, density=density)
    state = builder.build()
    mass, inertia = _read_back(state, index)
    np.testing.assert_allclose(mass, expected_mass, rtol=RTOL)
    np.testing.assert_allclose(inertia, expected_inertia, rtol=RTOL)
    assert index >= STATIC.num_polygons
    np.testing.assert_allclose(float(state.bodies.radius[index]), radius, rtol=RTOL)

    f_mass, f_inertia = circle_mass_properties(radius, density)
    np.testing.assert_allclose(float(f_mass), expected_mass, rtol=RTOL)
    np.testing.assert_allclose(float(f_inertia), expected_inertia, rtol=RTOL)


# --------------------------------------------------------------------------- statics
def test_static_shapes_have_zero_inverse_mass_and_inertia():
    builder = SceneBuilder(STATIC, boundaries=True)
    box = builder.add_box((2.0, 2.0), (0.5, 0.5), static=True, density=3.0)
    tri = builder.add_polygon((3.0, 2.0), TRIANGLES[0], static=True)
    circle = builder.add_circle((1.0, 1.0), 0.2, static=True)
    dynamic = builder.add_box((4.0, 2.0), (0.5, 0.5))
    b = builder.build().bodies
    for index in [0, 1, 2, 3, box, tri, circle]:
        assert float(b.inverse_mass[index]) == 0.0, index
        assert float(b.inverse_inertia[index]) == 0.0, index
        assert bool(b.is_static[index])
        assert bool(b.active[index])
    assert float(b.inverse_mass[dynamic]) > 0.0 and float(b.inverse_inertia[dynamic]) > 0.0


def test_boundaries_layout():
    """Reserved slots 0-3: floor top at y = 0.4 over x in [0, 5], walls at x = 0 and x = 5, ceiling at y = 5."""
    b = SceneBuilder(STATIC, boundaries=True).build().bodies
    world = [np.asarray(b.vertices[i], np.float64) + np.asarray(b.position[i], np.float64) for i in range(4)]
    for i in range(4):
        assert float(b.rotation[i]) == 0.0
    np.testing.assert_allclose(world[0][:, 1].max(), 0.4, rtol=RTOL)
    np.testing.assert_allclose([world[0][:, 0].min(), world[0][:, 0].max()], [0.0, 5.0], atol=1e-5)
    np.testing.assert_allclose(world[1][:, 0].max(), 0.0, atol=1e-5)
    np.testing.assert_allclose(world[2][:, 0].min(), 5.0, rtol=RTOL)
    np.testing.assert_allclose(world[3][:, 1].min(), 5.0, rtol=RTOL)


# --------------------------------------------------------------------------- orientation
@pytest.mark.parametrize("vertices", [TRIANGLES[0], TRAPEZOID])
def test_clockwise_vertices_are_reoriented(vertices):
    density = 1.5
    ccw_builder, cw_builder = _builder(), _builder()
    ccw = ccw_builder.add_polygon((2.0, 2.0), vertices, density=density)
    cw = cw_builder.add_polygon((2.0, 2.0), vertices[::-1].copy(), density=density)
    ccw_b, cw_b = ccw_builder.build().bodies, cw_builder.build().bodies
    n = len(vertices)
    stored = np.asarray(cw_b.vertices[cw], np.float64)[:n]
    assert int(cw_b.n_vertices[cw]) == n
    assert _signed_area(stored) > 0, "stored vertices must be counter-clockwise"
    np.testing.assert_allclose(_signed_area(stored), abs(_signed_area(vertices)), rtol=RTOL)
    for field in ("inverse_mass", "inverse_inertia"):
        np.testing.assert_allclose(float(getattr(cw_b, field)[cw]), float(getattr(ccw_b, field)[ccw]), rtol=RTOL)
        assert float(getattr(cw_b, field)[cw]) > 0
    np.testing.assert_allclose(np.asarray(cw_b.position[cw]), np.asarray(ccw_b.position[ccw]), rtol=RTOL)
    # Same vertex set, relative to the area centroid.
    assert {tuple(np.round(v, 5)) for v in stored} == {
        tuple(np.round(v, 5)) for v in np.asarray(ccw_b.vertices[ccw], np.float64)[:n]
    }
