"""SceneBuilder rejects invalid input with a ValueError that names the problem."""

from __future__ import annotations

import numpy as np
import pytest

from kforge.engine import SceneBuilder, StaticSimParams

pytestmark = pytest.mark.smoke

STATIC = StaticSimParams(num_polygons=6, num_circles=2, num_joints=2, num_thrusters=1)
N = STATIC.num_bodies
SQUARE = np.array([[-0.1, -0.1], [0.1, -0.1], [0.1, 0.1], [-0.1, 0.1]])


@pytest.fixture
def builder():
    return SceneBuilder(STATIC, boundaries=True)


# --------------------------------------------------------------------------- polygons
def test_non_convex_polygon(builder):
    dart = np.array([[0.0, 0.0], [0.4, 0.2], [0.0, 0.05], [-0.4, 0.2]])  # concave at (0, 0.05)
    with pytest.raises(ValueError, match="convex"):
        builder.add_polygon((2.0, 2.0), dart)


def test_self_intersecting_polygon(builder):
    bowtie = np.array([[0.0, 0.0], [0.2, 0.2], [0.2, 0.0], [0.0, 0.2]])
    with pytest.raises(ValueError, match="convex|degenerate"):
        builder.add_polygon((2.0, 2.0), bowtie)


@pytest.mark.parametrize(
    "vertices",
    [
        np.array([[0.0, 0.0], [0.1, 0.1], [0.2, 0.2]]),  # collinear
        np.array([[0.0, 0.0], [0.0, 0.0], [0.0, 0.0]]),  # one point
        np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1e-9], [0.0, 1e-9]]),  # zero area sliver
    ],
)
def test_degenerate_polygon(builder, vertices):
    with pytest.raises(ValueError, match="degenerate"):
        builder.add_polygon((2.0, 2.0), vertices)


def test_repeated_vertex_polygon(builder):
    vertices = np.array([[0.0, 0.0], [0.2, 0.0], [0.2, 0.0], [0.0, 0.2]])
    with pytest.raises(ValueError, match="convex|degenerate"):
        builder.add_polygon((2.0, 2.0), vertices)


@pytest.mark.parametrize("count", [0, 1, 2, 5, 8])
def test_wrong_vertex_count(builder, count):
    angles = np.linspace(0, 2 * np.pi, count, endpoint=False)
    vertices = 0.2 * np.stack([np.cos(angles), np.sin(angles)], -1)
    with pytest.raises(ValueError, match="3 to 4 vertices"):
        builder.add_polygon((2.0, 2.0), vertices)


def test_non_finite_vertices(builder):
    vertices = SQUARE.copy()
    vertices[1, 0] = np.nan
    with pytest.raises(ValueError, match="finite"):
        builder.add_polygon((2.0, 2.0), vertices)


@pytest.mark.parametrize("size", [(0.0, 1.0), (1.0, -0.5)])
def test_non_positive_box_size(builder, size):
    with pytest.raises(ValueError, match="size must be positive"):
        builder.add_box((2.0, 2.0), size)


# --------------------------------------------------------------------------- materials
@pytest.mark.parametrize("density", [0.0, -1.0, np.nan, np.inf])
def test_bad_density_for_movable_body(builder, density):
    with pytest.raises(ValueError, match="density must be positive"):
        builder.add_box((2.0, 2.0), (0.2, 0.2), density=density)
    with pytest.raises(ValueError, match="density must be positive"):
        builder.add_circle((2.0, 2.0), 0.2, density=density)


def test_zero_density_allowed_for_static_body(builder):
    index = builder.add_box((2.0, 2.0), (0.2, 0.2), density=0.0, static=True)
    assert float(builder.build().bodies.inverse_mass[index]) == 0.0


@pytest.mark.parametrize("radius", [0.0, -0.1, np.nan, np.inf])
def test_bad_radius(builder, radius):
    with pytest.raises(ValueError, match="radius must be positive"):
        builder.add_circle((2.0, 2.0), radius)


@pytest.mark.parametrize("restitution", [-0.01, 1.01, 2.0, np.nan])
def test_restitution_outside_unit_interval(builder, restitution):
    with pytest.raises(ValueError, match=r"restitution must be in \[0, 1\]"):
        builder.add_box((2.0, 2.0), (0.2, 0.2), restitution=restitution)
    with pytest.raises(ValueError, match=r"restitution must be in \[0, 1\]"):
        builder.add_circle((2.0, 2.0), 0.2, restitution=restitution)


@pytest.mark.parametrize("restitution", [0.0, 1.0])
def test_restitution_bounds_accepted(builder, restitution):
    builder.add_circle((2.0, 2.0), 0.2, restitution=restitution)


@pytest.mark.parametrize("mode", [-1, 3, 7])
def test_bad_collision_mode(builder, mode):
    with pytest.raises(ValueError, match="collision_mode"):
        builder.add_box((2.0, 2.0), (0.2, 0.2), collision_mode=mode)
    with pytest.raises(ValueError, match="collision_mode"):
        builder.add_circle((2.0, 2.0), 0.2, collision_mode=mode)


def test_negative_friction(builder):
    with pytest.raises(ValueError, match="friction"):
        builder.add_box((2.0, 2.0), (0.2, 0.2), friction=-0.1)


def test_non_finite_position(builder):
    with pytest.raises(ValueError, match="finite"):
        builder.add_circle((np.nan, 2.0), 0.2)


# --------------------------------------------------------------------------- joints
@pytest.mark.parametrize("bad", [-1, N, N + 5])
def test_joint_body_out_of_range(builder, bad):
    box = builder.add_box((2.0, 2.0), (0.2, 0.2))
    with pytest.raises(ValueError, match="out of range"):
        builder.add_revolute_joint(box, bad, (2.0, 2.0))
    with pytest.raises(ValueError, match="out of range"):
        builder.add_fixed_joint(bad, box, (2.0, 2.0))


def test_joint_on_empty_slot(builder):
    box = builder.add_box((2.0, 2.0), (0.2, 0.2))
    empty_circle = STATIC.num_polygons  # no circle added yet
    with pytest.raises(ValueError, match="empty slot"):
        builder.add_revolute_joint(box, empty_circle, (2.0, 2.0))
    with pytest.raises(ValueError, match="empty slot"):
        builder.add_fixed_joint(box + 1, box, (2.0, 2.0))


def test_joint_with_itself(builder):
    box = builder.add_box((2.0, 2.0), (0.2, 0.2))
    with pytest.raises(ValueError, match="two different bodies"):
        builder.add_revolute_joint(box, box, (2.0, 2.0))
    with pytest.raises(ValueError, match="two different bodies"):
        builder.add_fixed_joint(box, box, (2.0, 2.0))


@pytest.mark.parametrize("limits", [(0.1, 0.5), (-0.5, -0.1), (0.5, -0.5)])
def test_joint_limits_must_contain_zero(builder, limits):
    a = builder.add_box((2.0, 2.0), (0.2, 0.2))
    b = builder.add_box((2.2, 2.0), (0.2, 0.2))
    with pytest.raises(ValueError, match="lower <= 0 <= upper"):
        builder.add_revolute_joint(a, b, (2.1, 2.0), limits=limits)


def test_joint_limits_containing_zero_accepted(builder):
    a = builder.add_box((2.0, 2.0), (0.2, 0.2))
    b = builder.add_box((2.2, 2.0), (0.2, 0.2))
    index = builder.add_revolute_joint(a, b, (2.1, 2.0), limits=(-0.5, 0.0))
    joints = builder.build().joints
    assert bool(joints.has_limits[index])
    np.testing.assert_allclose([float(joints.lower_angle[index]), float(joints.upper_angle[index])], [-0.5, 0.0])


def test_joint_slots_exhausted(builder):
    a = builder.add_box((2.0, 2.0), (0.2, 0.2))
    b = builder.add_box((2.2, 2.0), (0.2, 0.2))
    for _ in range(STATIC.num_joints):
        builder.add_revolute_joint(a, b, (2.1, 2.0))
    with pytest.raises(ValueError, match="no free joint slot"):
        builder.add_fixed_joint(a, b, (2.1, 2.0))


# --------------------------------------------------------------------------- thrusters
@pytest.mark.parametrize("bad", [-1, N, 100])
def test_thruster_body_out_of_range(builder, bad):
    with pytest.raises(ValueError, match="thruster body index .* out of range"):
        builder.add_thruster(bad, (2.0, 2.0), 0.0, 1.0)


def test_thruster_on_empty_slot(builder):
    with pytest.raises(ValueError, match="empty slot"):
        builder.add_thruster(STATIC.num_polygons, (2.0, 2.0), 0.0, 1.0)


def test_thruster_negative_power(builder):
    box = builder.add_box((2.0, 2.0), (0.2, 0.2))
    with pytest.raises(ValueError, match="power"):
        builder.add_thruster(box, (2.0, 2.0), 0.0, -1.0)


def test_thruster_slots_exhausted(builder):
    box = builder.add_box((2.0, 2.0), (0.2, 0.2))
    for _ in range(STATIC.num_thrusters):
        builder.add_thruster(box, (2.0, 2.0), 0.0, 1.0)
    with pytest.raises(ValueError, match="no free thruster slot"):
        builder.add_thruster(box, (2.0, 2.0), 0.0, 1.0)


# --------------------------------------------------------------------------- slots
def test_polygon_slots_exhausted(builder):
    for k in range(STATIC.num_polygons - STATIC.num_reserved_static):
        builder.add_box((1.0 + 0.5 * k, 2.0), (0.2, 0.2))
    with pytest.raises(ValueError, match="no free polygon slot"):
        builder.add_box((4.0, 2.0), (0.2, 0.2))
    # Static polygons do not get the reserved slots implicitly either.
    with pytest.raises(ValueError, match="no free polygon slot"):
        builder.add_box((4.0, 2.0), (0.2, 0.2), static=True)


def test_circle_slots_exhausted(builder):
    for k in range(STATIC.num_circles):
        builder.add_circle((1.0 + 0.5 * k, 2.0), 0.1)
    with pytest.raises(ValueError, match="no free circle slot"):
        builder.add_circle((4.0, 2.0), 0.1)


def test_explicit_slot_already_used(builder):
    builder.add_circle((1.0, 2.0), 0.1, slot=1)
    with pytest.raises(ValueError, match="already used"):
        builder.add_circle((2.0, 2.0), 0.1, slot=1)
    with pytest.raises(ValueError, match="already used"):
        builder.add_box((2.0, 2.0), (0.2, 0.2), static=True, slot=0)  # the floor


@pytest.mark.parametrize("slot", [-1, 6, 99])
def test_explicit_slot_out_of_range(builder, slot):
    with pytest.raises(ValueError, match="out of range"):
        builder.add_box((2.0, 2.0), (0.2, 0.2), slot=slot)


def test_dynamic_body_in_reserved_static_slot():
    builder = SceneBuilder(STATIC, boundaries=False)
    for slot in range(STATIC.num_reserved_static):
        with pytest.raises(ValueError, match="reserved for static"):
            builder.add_box((2.0, 2.0), (0.2, 0.2), slot=slot)
    # A static body may go there.
    index = builder.add_box((2.0, 2.0), (0.2, 0.2), static=True, slot=2)
    assert index == 2


def test_boundaries_need_reserved_slots():
    with pytest.raises(ValueError, match="num_reserved_static"):
        SceneBuilder(StaticSimParams(num_polygons=6, num_circles=2, num_reserved_static=2), boundaries=True)


def test_static_params_validation():
    with pytest.raises(ValueError, match="num_polygons"):
        StaticSimParams(num_polygons=-1)
    with pytest.raises(ValueError, match="exceeds"):
        StaticSimParams(num_polygons=3, num_reserved_static=4)
    with pytest.raises(ValueError, match="num_substeps must be >= 1"):
        StaticSimParams(num_substeps=0)
    with pytest.raises(ValueError, match="num_iterations must be >= 1"):
        StaticSimParams(num_iterations=0)
    with pytest.raises(ValueError, match="num_relax_iterations must be >= 0"):
        StaticSimParams(num_relax_iterations=-1)
    with pytest.raises(ValueError, match="unknown size"):
        StaticSimParams.for_size("xl")


def test_failed_add_leaves_builder_usable(builder):
    with pytest.raises(ValueError):
        builder.add_box((2.0, 2.0), (0.2, 0.2), density=-1.0)
    index = builder.add_box((2.0, 2.0), (0.2, 0.2))
    assert index == STATIC.num_reserved_static
    state = builder.build()
    assert int(np.sum(np.asarray(state.bodies.active))) == 5
