"""Where a contact's points lie and how deep they count (`StaticSimParams.contact_points`): ours midway between the
surfaces, each point with its own depth, or Jax2D's placement (docs/physics.md, docs/fidelity.md).

Every test prints a `MEASURED` line (run pytest with -s to see them).
"""

from __future__ import annotations

import dataclasses
import math

import jax.numpy as jnp
import numpy as np
import pytest
from engine_test_helpers import SIZE_S, pair_index, zero_gravity

from kforge.engine import FLOOR_TOP, ContactLaw, ContactPoints, SceneBuilder, SimParams, StaticSimParams, pair_layout
from kforge.engine.collision import manifolds, world_geometry
from kforge.engine.params import ContactPoints as ContactPointsFromParams
from tests.helpers import measured
from tests.rollouts import run_scene

FLOOR = 0
"""A `SceneBuilder`'s floor: reserved polygon slot 0, its top at `engine.FLOOR_TOP`."""
JAX2D_SCHEME = dict(num_substeps=1, num_iterations=10, num_relax_iterations=0)
"""Jax2D's solver scheme in ours: one step of 10 passes, positions advanced after the last."""


def _pair_manifold(builder: SceneBuilder, body_a: int, body_b: int, points: ContactPoints):
    """(normal, points, separations, valid) of the pair {body_a, body_b}, with a 5 cm speculative margin."""
    state = builder.build()
    layout = pair_layout(SIZE_S)
    margin = jnp.full(layout.body_a.shape, 0.05)
    found = manifolds(world_geometry(state.bodies), layout, margin, points == ContactPoints.KINETIX)
    k = pair_index(SIZE_S, body_a, body_b)
    return tuple(np.asarray(x[k], np.float64) for x in (found.normal, found.point, found.separation, found.valid))


def test_the_enum_is_the_engines_public_one():
    assert ContactPoints is ContactPointsFromParams
    assert StaticSimParams().contact_points == ContactPoints.MIDWAY


def test_two_overlapping_circles_touch_midway_or_on_the_first_circles_surface():
    """Circles of radius 0.3 and 0.2, centres 0.4 m apart: 10 cm of overlap along +x. Midway the point is 0.25 m
    from the first centre; Jax2D puts it on the first circle's surface, 0.3 m from it. The depth is the same."""
    points = {}
    for law in ContactPoints:
        builder = SceneBuilder(SIZE_S)
        a = builder.add_circle((2.0, 1.0), 0.3)
        b = builder.add_circle((2.4, 1.0), 0.2)
        normal, point, separation, valid = _pair_manifold(builder, a, b, law)
        points[law] = point[0]
        np.testing.assert_allclose(normal, [1.0, 0.0], atol=1e-6)
        assert separation[0] == pytest.approx(-0.1, abs=1e-6) and valid[0] and not valid[1]
    measured("two circles", midway=points[ContactPoints.MIDWAY], kinetix=points[ContactPoints.KINETIX])
    np.testing.assert_allclose(points[ContactPoints.MIDWAY], [2.25, 1.0], atol=1e-6)
    np.testing.assert_allclose(points[ContactPoints.KINETIX], [2.3, 1.0], atol=1e-6)


def test_a_circle_in_the_floor_touches_midway_or_on_the_floors_surface():
    """A circle of radius 0.25 whose centre is 15 cm above the floor's top (10 cm in it): midway the point is 5 cm
    below the top, in Jax2D's placement on the top itself."""
    heights = {}
    for law in ContactPoints:
        builder = SceneBuilder(SIZE_S)
        disc = builder.add_circle((2.5, FLOOR_TOP + 0.15), 0.25)
        normal, point, separation, _ = _pair_manifold(builder, FLOOR, disc, law)
        heights[law] = point[0, 1]
        np.testing.assert_allclose(normal, [0.0, 1.0], atol=1e-6)
        assert point[0, 0] == pytest.approx(2.5, abs=1e-6)
        assert separation[0] == pytest.approx(-0.1, abs=1e-6)
    measured("circle in the floor", point_heights={int(k): v for k, v in heights.items()})
    assert heights[ContactPoints.MIDWAY] == pytest.approx(FLOOR_TOP - 0.05, abs=1e-6)
    assert heights[ContactPoints.KINETIX] == pytest.approx(FLOOR_TOP, abs=1e-6)


def _tilted_box_in_the_floor(law: ContactPoints, lowest_depth: float, height_difference: float):
    """Manifold of a 0.5 m box turned so that its bottom corners differ in height by `height_difference` [m], the
    lower one `lowest_depth` [m] in the floor; also the corners' own separations (low, high)."""
    size = 0.5
    angle = math.asin(height_difference / size)
    half_diagonal_drop = 0.5 * size * (math.cos(angle) + math.sin(angle))  # centre above the lowest corner
    builder = SceneBuilder(SIZE_S)
    box = builder.add_box((2.5, FLOOR_TOP - lowest_depth + half_diagonal_drop), (size, size), rotation=angle)
    own = (-lowest_depth, height_difference - lowest_depth)
    return _pair_manifold(builder, FLOOR, box, law), own


def test_a_tilted_box_in_the_floor_pushes_both_corners_at_the_pairs_deepest_overlap_in_jax2ds_placement():
    """Bottom corners 4 cm and 1 cm in the floor. Midway, each point counts its own depth and lies halfway between
    its corner and the floor's top; in Jax2D's placement both points lie at the box's corners and both count the
    pair's deepest overlap, 4 cm, so the shallow corner is pushed out as hard as the deep one."""
    (normal, point, separation, valid), own = _tilted_box_in_the_floor(ContactPoints.MIDWAY, 0.04, 0.03)
    (k_normal, k_point, k_separation, k_valid), _ = _tilted_box_in_the_floor(ContactPoints.KINETIX, 0.04, 0.03)
    measured("tilted box", midway=separation, kinetix=k_separation, corners=own)
    np.testing.assert_allclose(normal, [0.0, 1.0], atol=1e-6)
    np.testing.assert_allclose(k_normal, normal, atol=1e-6)
    assert valid.all() and k_valid.all()
    np.testing.assert_allclose(sorted(separation), sorted(own), atol=1e-5)
    np.testing.assert_allclose(k_separation, [-0.04, -0.04], atol=1e-5)
    corner_heights = sorted(FLOOR_TOP + s for s in own)
    np.testing.assert_allclose(sorted(k_point[:, 1]), corner_heights, atol=1e-5)
    np.testing.assert_allclose(sorted(point[:, 1]), [FLOOR_TOP + 0.5 * s for s in sorted(own)], atol=1e-5)


def test_a_corner_above_the_floor_keeps_its_own_separation_in_jax2ds_placement():
    """Corners 2 cm in the floor and 1 cm above it (within the 5 cm margin): only the overlapping corner takes the
    pair's depth; the other stays a speculative point at its own separation."""
    (_, _, separation, valid), own = _tilted_box_in_the_floor(ContactPoints.KINETIX, 0.02, 0.03)
    measured("box with one corner above the floor", kinetix=separation, corners=own)
    assert valid.all()
    np.testing.assert_allclose(sorted(separation), sorted(own), atol=1e-5)


def _spinning_disc_in_the_floor(law: ContactPoints, depth: float, radius: float, spin: float):
    """Angular velocity after one step [rad/s], mass [kg] and inertia [kg m^2] of a disc that starts `depth` in the
    floor spinning at `spin`, in zero gravity, under Jax2D's contact law and scheme."""
    builder = SceneBuilder(SIZE_S)
    disc = builder.add_circle((2.5, FLOOR_TOP + radius - depth), radius, angular_velocity=spin)
    state = zero_gravity(builder.build())
    params = SimParams(speculative_distance=0.0, speculative_reach=0.0)
    static = dataclasses.replace(SIZE_S, contact_law=ContactLaw.BAUMGARTE, contact_points=law, **JAX2D_SCHEME)
    _, traj = run_scene(state, static, 1, params=params)
    mass = 1.0 / float(state.bodies.inverse_mass[disc])
    inertia = 1.0 / float(state.bodies.inverse_inertia[disc])
    return float(traj.angular_velocity[-1, disc]), mass, inertia


def test_where_the_point_lies_sets_frictions_lever_arm():
    """A disc (radius 0.25 m) spinning at 2 rad/s, 10 cm in the floor: friction stops the slip of the contact point
    within the step, so the disc rolls on at w = w0 I / (I + m l^2), l the distance from its centre to the point
    (angular momentum about the point is kept). Midway l = r - depth / 2 = 0.2 m; on the floor's surface, as in Jax2D,
    l = r - depth = 0.15 m."""
    depth, radius, spin = 0.1, 0.25, 2.0
    for law, lever in ((ContactPoints.MIDWAY, radius - 0.5 * depth), (ContactPoints.KINETIX, radius - depth)):
        rolled, mass, inertia = _spinning_disc_in_the_floor(law, depth, radius, spin)
        expected = spin * inertia / (inertia + mass * lever**2)
        measured(f"spinning disc, {law.name}", rolled=rolled, expected=expected, lever=lever)
        assert rolled == pytest.approx(expected, rel=1e-4)
