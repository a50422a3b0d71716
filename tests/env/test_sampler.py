"""Random level sampler: determinism, validity invariants, and statistics against Kinetix's measured distribution.

Reference figures: Kinetix's sampler over 1,024 levels per size (docs/kinetix.md, random level distribution). Our
samples are compared with a two-sample test: |ours - table| <= Z_LIMIT * sqrt(se_ours^2 + se_table^2) + the table's
rounding.
"""

from __future__ import annotations

import math

import jax
import numpy as np
import pytest

from kforge.engine import SceneBuilder, StaticSimParams
from kforge.env import EnvParams, Role, StaticEnvParams
from kforge.env.rollout import Outcome, Policy, first_episode_outcomes
from kforge.env.sampler import sample_level, sample_levels

NUM_LEVELS = 1024
TABLE_LEVELS = 1024  # levels behind each figure of Kinetix's table
Z_LIMIT = 4.0
SEED = 20240611

# Kinetix's sampler statistics (docs/kinetix.md). Histograms count levels with 0, 1, 2, ... items.
TABLE = {
    "s": {
        "polygons": [0, 1024],
        "circles": [0, 0, 1024],
        "joints": [320, 704],
        "thrusters": [354, 670],
        "motor_on_mean": 0.53,
        "fixated_mean": 0.0,
        "red_mean": 0.08,
        "rates": {Policy.NOOP: (18.8, 9.6, 71.6), Policy.UNIFORM_RANDOM: (35.7, 10.1, 54.2)},
    },
    "m": {
        "polygons": [1, 87, 936],
        "circles": [0, 52, 463, 509],
        "joints": [126, 426, 472],
        "thrusters": [255, 581, 188],
        "motor_on_mean": 1.06,
        "fixated_mean": 1.37,
        "red_mean": 0.22,
        "rates": {Policy.NOOP: (12.5, 7.6, 79.9), Policy.UNIFORM_RANDOM: (22.0, 9.0, 69.0)},
    },
    "l": {
        "polygons_mean": 6.07,
        "circles": [3, 40, 167, 291, 523],
        "shapes_mean": 9.33,
        "joints_mean": 3.91,
        "revolute_mean": 2.88,
        "fixed_mean": 1.03,
        "thrusters": [255, 581, 188],
        "motor_on_mean": 2.33,
        "fixated_mean": 2.89,
        "red_mean": 0.70,
        "rates": {Policy.NOOP: (8.6, 13.4, 78.0), Policy.UNIFORM_RANDOM: (13.8, 16.7, 69.5)},
    },
}
FLOOR_ROLES = {Role.DEFAULT: 917, Role.GREEN: 0, Role.BLUE: 25, Role.RED: 82}
BLUE_SHAPE_FRACTION = 0.98  # levels whose blue is a movable or fixated shape (not the floor)
MEAN_ROUNDING = 0.005  # table means are given to two decimals
RATE_ROUNDING = 0.0005  # rates to 0.1 %

SIZES = [
    "s",
    pytest.param("m", marks=pytest.mark.slow),
    pytest.param("l", marks=pytest.mark.slow),
]


@pytest.fixture(scope="module")
def sampled():
    cache = {}

    def get(size: str):
        if size not in cache:
            static = StaticEnvParams.for_size(size)
            keys = jax.random.split(jax.random.PRNGKey(SEED), NUM_LEVELS)
            cache[size] = (static, jax.tree.map(np.asarray, sample_levels(keys, static)))
        return cache[size]

    return get


def _take(levels, index):
    return jax.tree.map(lambda x: x[index], levels)


def _rotate(angle, vector):
    c, s = np.cos(angle), np.sin(angle)
    return np.stack([c * vector[..., 0] - s * vector[..., 1], s * vector[..., 0] + c * vector[..., 1]], -1)


# --------------------------------------------------------------------------- determinism
def test_same_key_same_level_and_keys_differ(sampled):
    static, levels = sampled("s")
    again = sample_levels(jax.random.split(jax.random.PRNGKey(SEED), NUM_LEVELS), static)
    for a, b in zip(jax.tree.leaves(levels), jax.tree.leaves(again), strict=True):
        np.testing.assert_array_equal(a, np.asarray(b))
    positions = levels.sim.bodies.position[:8, static.sim.num_reserved_static :]
    for i in range(1, len(positions)):
        assert not np.array_equal(positions[0], positions[i])


def test_single_level_matches_batch():
    static = StaticEnvParams.for_size("s")
    keys = jax.random.split(jax.random.PRNGKey(2), 8)
    batch = sample_levels(keys, static)
    single = jax.jit(sample_level, static_argnames="static")(keys[5], static)
    for a, b in zip(jax.tree.leaves(single), jax.tree.leaves(_take(batch, 5)), strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-6, atol=1e-6)


def test_rejects_too_small_static():
    static = StaticEnvParams(sim=StaticSimParams(num_joints=0))
    with pytest.raises(ValueError, match="free shape slots"):
        sample_level(jax.random.PRNGKey(0), static)


# --------------------------------------------------------------------------- validity invariants
def _connected_groups(body_a, body_b, active, n):
    group = list(range(n))

    def find(i):
        while group[i] != i:
            i = group[i]
        return i

    for a, b, on in zip(body_a, body_b, active, strict=True):
        if on:
            group[find(a)] = find(b)
    return np.array([find(i) for i in range(n)])


@pytest.mark.parametrize("size", SIZES)
def test_levels_are_valid(sampled, size):
    static, levels = sampled(size)
    p, n, reserved = static.sim.num_polygons, static.num_bodies, static.sim.num_reserved_static
    b, j, t, task = levels.sim.bodies, levels.sim.joints, levels.sim.thrusters, levels.task

    # Slots 0-3 are exactly the builder's boundaries.
    boundary = SceneBuilder(static.sim).build().bodies
    for name in ("position", "rotation", "inverse_mass", "vertices", "n_vertices", "collision_mode", "active"):
        np.testing.assert_array_equal(
            getattr(b, name)[:, :reserved],
            np.broadcast_to(getattr(boundary, name)[:reserved], getattr(b, name)[:, :reserved].shape),
        )

    roles = np.where(b.active, task.roles, -1)
    assert np.all(np.sum(roles == Role.GREEN, 1) == 1)
    assert np.all(np.sum(roles == Role.BLUE, 1) == 1)
    assert np.all(np.sum(roles == Role.RED, 1) <= 1)
    assert np.all(roles[:, 1:reserved] == Role.DEFAULT)

    # Polygons: counter-clockwise convex rectangles; circles: positive radius, no vertices.
    polygon_active = b.active[:, reserved:p]
    vertices = b.vertices[:, reserved:p]
    edges = np.roll(vertices, -1, axis=2) - vertices
    turns = edges[..., 0] * np.roll(edges, -1, 2)[..., 1] - edges[..., 1] * np.roll(edges, -1, 2)[..., 0]
    assert np.all(turns[polygon_active] > 0)
    assert np.all(b.n_vertices[:, reserved:p][polygon_active] == 4)
    width = vertices[..., 1, 0] - vertices[..., 0, 0]
    height = vertices[..., 2, 1] - vertices[..., 1, 1]
    assert np.all(width[polygon_active] > 0) and np.all(height[polygon_active] > 0)
    assert np.all(b.radius[:, p:][b.active[:, p:]] >= 0.1 - 1e-6)

    # Mass properties from density and the analytic area/inertia of rectangles and discs.
    movable = b.active & (b.inverse_mass > 0)
    density = task.densities
    mass = np.where(np.arange(n) < p, 0.0, density * math.pi * b.radius**2)
    mass[:, reserved:p] = density[:, reserved:p] * width * height
    inertia = np.where(np.arange(n) < p, 0.0, 0.25 * mass * b.radius**2)  # Kinetix's sampler: m r^2 / 4
    inertia[:, reserved:p] = mass[:, reserved:p] * (width**2 + height**2) / 12.0
    np.testing.assert_allclose(b.inverse_mass[movable], 1.0 / mass[movable], rtol=1e-4)
    np.testing.assert_allclose(b.inverse_inertia[movable], 1.0 / inertia[movable], rtol=1e-4)
    assert np.all(density[:, reserved:][b.active[:, reserved:]] == 1.0)
    fixated = b.active & (b.inverse_mass == 0)
    assert np.all(b.inverse_inertia[fixated] == 0)
    if size == "s":
        assert not np.any(fixated[:, reserved:])

    # Joints join two different active bodies at one world point; fixed joints hold the start pose, revolute joints
    # have reference angle 0 as in Kinetix (their limits bound the absolute relative rotation).
    levels_index = np.arange(b.active.shape[0])[:, None]
    on = j.active
    assert np.all(b.active[levels_index, j.body_a][on]) and np.all(b.active[levels_index, j.body_b][on])
    assert np.all((j.body_a != j.body_b)[on])
    world_a = b.position[levels_index, j.body_a] + _rotate(b.rotation[levels_index, j.body_a], j.anchor_a)
    world_b = b.position[levels_index, j.body_b] + _rotate(b.rotation[levels_index, j.body_b], j.anchor_b)
    np.testing.assert_allclose(world_a[on], world_b[on], atol=1e-4)
    relative = b.rotation[levels_index, j.body_b] - b.rotation[levels_index, j.body_a]
    fixed, revolute = on & j.is_fixed, on & ~j.is_fixed
    np.testing.assert_allclose(j.reference_angle[fixed], relative[fixed], atol=1e-5)
    assert np.all(j.reference_angle[revolute] == 0.0)
    assert np.all(j.lower_angle[on] <= 0) and np.all(j.upper_angle[on] >= 0)
    assert not np.any((j.is_fixed & (j.motor_on | j.has_limits))[on])
    assert np.all((task.motor_bindings >= 0) & (task.motor_bindings < 4))

    # Thrusters sit on movable shapes, within the shape; bindings in range.
    ton = t.active
    assert np.all(movable[levels_index, t.body][ton])
    reach = np.where(
        t.body < p,
        np.linalg.norm(np.max(np.abs(b.vertices[levels_index, t.body]), axis=2), axis=-1),
        b.radius[levels_index, t.body],
    )
    assert np.all(np.linalg.norm(t.anchor, axis=-1)[ton] <= reach[ton] + 1e-5)
    assert np.all((task.thruster_bindings >= 0) & (task.thruster_bindings < 2))

    # Every level has a revolute joint or a thruster.
    assert np.all(np.any(on & ~j.is_fixed, 1) | np.any(ton, 1))

    # Collision matrix: False exactly inside joint-connected groups.
    for level in range(0, b.active.shape[0], 17):
        groups = _connected_groups(j.body_a[level], j.body_b[level], on[level], n)
        np.testing.assert_array_equal(levels.sim.collision_matrix[level], groups[:, None] != groups[None, :])


# --------------------------------------------------------------------------- statistics
def _check_histogram(name, ours, table_counts):
    ours_fraction = np.bincount(ours, minlength=len(table_counts)) / len(ours)
    assert len(ours_fraction) == len(table_counts), f"{name}: values beyond the table's range: {ours_fraction}"
    table_fraction = np.asarray(table_counts) / TABLE_LEVELS
    for k, (a, b) in enumerate(zip(ours_fraction, table_fraction, strict=True)):
        p = (a * len(ours) + b * TABLE_LEVELS) / (len(ours) + TABLE_LEVELS)
        se = math.sqrt(max(p * (1 - p), 1.0 / TABLE_LEVELS) * (1 / len(ours) + 1 / TABLE_LEVELS))
        assert abs(a - b) <= Z_LIMIT * se, f"{name}[{k}]: ours {a:.3f} vs table {b:.3f} (se {se:.3f})"


def _check_mean(name, ours, table_mean):
    se = max(np.std(ours), 0.1) * math.sqrt(1 / len(ours) + 1 / TABLE_LEVELS)
    assert abs(np.mean(ours) - table_mean) <= Z_LIMIT * se + MEAN_ROUNDING, (
        f"{name}: ours {np.mean(ours):.3f} vs table {table_mean} (se {se:.3f})"
    )


@pytest.mark.parametrize("size", SIZES)
def test_statistics_match_kinetix(sampled, size):
    static, levels = sampled(size)
    table = TABLE[size]
    p, reserved = static.sim.num_polygons, static.sim.num_reserved_static
    b, j, t = levels.sim.bodies, levels.sim.joints, levels.sim.thrusters
    polygons = b.active[:, reserved:p].sum(1)
    circles = b.active[:, p:].sum(1)
    counts = {
        "polygons": polygons,
        "circles": circles,
        "shapes": polygons + circles,
        "joints": j.active.sum(1),
        "revolute": (j.active & ~j.is_fixed).sum(1),
        "fixed": (j.active & j.is_fixed).sum(1),
        "motor_on": (j.active & ~j.is_fixed & j.motor_on).sum(1),
        "thrusters": t.active.sum(1),
        "fixated": (b.active & (b.inverse_mass == 0))[:, reserved:].sum(1),
        "red": (np.where(b.active, levels.task.roles, -1)[:, reserved:] == Role.RED).sum(1),
    }
    checked = 0
    for key, reference in table.items():
        name = key.removesuffix("_mean")
        if key == "rates":
            continue
        if key.endswith("_mean"):
            _check_mean(f"{size} {name}", counts[name], reference)
        else:
            _check_histogram(f"{size} {name}", counts[name], reference)
        checked += 1
    assert checked >= 7

    floor = levels.task.roles[:, 0]
    _check_histogram(f"{size} floor", floor, [FLOOR_ROLES[r] for r in Role])
    blue_shape = np.any(np.where(b.active, levels.task.roles, -1)[:, reserved:] == Role.BLUE, 1)
    _check_histogram(
        f"{size} blue shape",
        blue_shape.astype(int),
        [round((1 - BLUE_SHAPE_FRACTION) * 1024), round(BLUE_SHAPE_FRACTION * 1024)],
    )


@pytest.mark.slow
@pytest.mark.parametrize("size", ["s", "m", "l"])
@pytest.mark.parametrize("policy", [Policy.NOOP, Policy.UNIFORM_RANDOM])
def test_first_episode_rates_match_kinetix(sampled, size, policy):
    """Success / red / timeout rates of the first episode, as in the table (our physics differs slightly)."""
    static, levels = sampled(size)
    result = first_episode_outcomes(levels, EnvParams(), static, policy, key=jax.random.PRNGKey(SEED))
    outcome = np.asarray(result.outcome)
    ours = [np.mean(outcome == o) for o in (Outcome.SUCCESS, Outcome.FAILURE)]
    ours.append(np.mean((outcome == Outcome.TIMEOUT) | (outcome == Outcome.UNSTABLE)))
    for name, a, b in zip(("success", "red", "timeout"), ours, TABLE[size]["rates"][policy], strict=True):
        b = b / 100
        se = math.sqrt(b * (1 - b) * (1 / NUM_LEVELS + 1 / TABLE_LEVELS))
        assert abs(a - b) <= Z_LIMIT * se + RATE_ROUNDING, f"{size} {policy.name} {name}: ours {a:.3f} vs {b:.3f}"
