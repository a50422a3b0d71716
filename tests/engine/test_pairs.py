"""Candidate pair layout, solver colours, and the joint collision filter."""

from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from kforge.engine import StaticSimParams, empty_state, pair_layout
from kforge.engine.collision_filter import joint_collision_matrix

SIZES = [
    StaticSimParams.for_size("s"),
    StaticSimParams.for_size("m"),
    StaticSimParams.for_size("l"),
    StaticSimParams(num_polygons=3, num_circles=0, num_reserved_static=0),
    StaticSimParams(num_polygons=4, num_circles=5, num_reserved_static=0),
    StaticSimParams(num_polygons=4, num_circles=1, num_reserved_static=4),
    StaticSimParams(num_polygons=0, num_circles=4, num_reserved_static=0),
]


@pytest.mark.parametrize("static", SIZES, ids=str)
def test_every_pair_listed_once(static):
    layout = pair_layout(static)
    n, p, reserved = static.num_bodies, static.num_polygons, static.num_reserved_static
    got = [tuple(sorted((int(a), int(b)))) for a, b in zip(layout.body_a, layout.body_b, strict=True)]
    expected = {(a, b) for a, b in itertools.combinations(range(n), 2) if not (a < reserved and b < reserved)}
    assert len(got) == len(set(got)), "a pair is listed twice"
    assert set(got) == expected
    assert (
        layout.num_pairs
        == len(expected)
        == layout.num_polygon_polygon + layout.num_polygon_circle + layout.num_circle_circle
    )
    assert layout.num_bodies == n
    # Type blocks in order polygon-polygon, polygon-circle (polygon first), circle-circle.
    kinds = [(int(a) >= p) + (int(b) >= p) for a, b in zip(layout.body_a, layout.body_b, strict=True)]
    assert kinds == sorted(kinds)
    assert kinds.count(0) == layout.num_polygon_polygon
    assert kinds.count(1) == layout.num_polygon_circle
    assert kinds.count(2) == layout.num_circle_circle
    assert np.all(layout.body_a < layout.body_b)


@pytest.mark.parametrize("static", SIZES, ids=str)
def test_colours_cover_pairs_and_never_repeat_a_movable_body(static):
    layout = pair_layout(static)
    k, n, reserved = layout.num_pairs, static.num_bodies, static.num_reserved_static
    slots = np.asarray(layout.colour_slots)
    real = slots[slots < k]
    assert np.all(slots <= k)
    assert sorted(real.tolist()) == list(range(k)), "every pair in exactly one colour"
    for colour in range(layout.num_colours):
        used = []
        for slot, a, b in zip(slots[colour], layout.colour_body_a[colour], layout.colour_body_b[colour], strict=True):
            if slot == k:
                assert a == n and b == n, "padding slots point at the dummy body"
                continue
            assert (a, b) == (layout.body_a[slot], layout.body_b[slot])
            used += [int(x) for x in (a, b) if x >= reserved]
        assert len(used) == len(set(used)), f"colour {colour} repeats a movable body: {sorted(used)}"


def _joints(static, pairs, active=None):
    joints = empty_state(static).joints
    count = static.num_joints
    body_a = np.zeros(count, np.int32)
    body_b = np.zeros(count, np.int32)
    flags = np.zeros(count, bool)
    for j, (a, b) in enumerate(pairs):
        body_a[j], body_b[j] = a, b
        flags[j] = True if active is None else active[j]
    return joints.replace(body_a=jnp.asarray(body_a), body_b=jnp.asarray(body_b), active=jnp.asarray(flags))


def _expected(num_bodies, groups):
    allowed = ~np.eye(num_bodies, dtype=bool)
    for group in groups:
        for a in group:
            for b in group:
                allowed[a, b] = False
    return allowed


FILTER_STATIC = StaticSimParams(num_polygons=6, num_circles=3, num_joints=4, num_thrusters=0)
jitted_matrix = jax.jit(joint_collision_matrix, static_argnums=1)


def test_joint_chain_disables_pairs_transitively():
    n = FILTER_STATIC.num_bodies
    # Chain A-B-C = 4-7-2 (A-C not directly jointed), a separate pair 5-8, and an inactive joint 0-6.
    joints = _joints(FILTER_STATIC, [(4, 7), (2, 7), (5, 8), (0, 6)], active=[True, True, True, False])
    got = np.asarray(jitted_matrix(joints, n))
    expected = _expected(n, [(4, 7, 2), (5, 8)])
    assert got.dtype == bool and got.shape == (n, n)
    np.testing.assert_array_equal(got, expected)
    assert not got[4, 2] and not got[2, 4], "A-C across the chain must not collide"
    assert got[0, 6], "an inactive joint disables nothing"


def test_long_chain_closure():
    """A path through every body needs paths of length N-1: everything is one group."""
    static = StaticSimParams(num_polygons=6, num_circles=3, num_joints=8, num_thrusters=0)
    n = static.num_bodies
    order = [3, 0, 8, 5, 1, 7, 2, 6, 4]
    joints = _joints(static, list(zip(order[:-1], order[1:], strict=True)))
    got = np.asarray(jitted_matrix(joints, n))
    np.testing.assert_array_equal(got, np.zeros((n, n), bool))
    # Dropping the middle joint splits the chain into two groups.
    split = _joints(static, list(zip(order[:-1], order[1:], strict=True)), active=[True] * 3 + [False] + [True] * 4)
    got = np.asarray(jitted_matrix(split, n))
    np.testing.assert_array_equal(got, _expected(n, [order[:4], order[4:]]))


def test_no_joints_only_diagonal():
    n = FILTER_STATIC.num_bodies
    got = np.asarray(jitted_matrix(_joints(FILTER_STATIC, []), n))
    np.testing.assert_array_equal(got, ~np.eye(n, dtype=bool))


def test_filter_vmaps_over_scenes():
    n = FILTER_STATIC.num_bodies
    scenes = [[(0, 1)], [(4, 7), (7, 2)], []]
    batch = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *[_joints(FILTER_STATIC, s) for s in scenes])
    got = np.asarray(jax.jit(jax.vmap(joint_collision_matrix, in_axes=(0, None)), static_argnums=1)(batch, n))
    for i, scene in enumerate(scenes):
        groups = [tuple(sorted({x for pair in scene for x in pair}))] if scene else []
        np.testing.assert_array_equal(got[i], _expected(n, groups))
