"""Test group E: invariants over random scenes (overlaps, joints, motors, thrusters, random actions), every step.

One vmapped scan of `ROLLOUT_STEPS` steps over `BATCH` random scenes of size m serves most tests; a second run
of the same scenes with junk in the inactive slots checks that inactive data is ignored; a zero-gravity batch
without static bodies checks momentum and energy.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from engine_test_helpers import PARAMS, SIZE_M, bounding_radius, kinetic_energy, masses, random_scene

from kforge.engine import SceneBuilder, pair_layout
from kforge.engine.collision_filter import modes_collide
from tests.helpers import stack, to_numpy
from tests.rollouts import BATCH, random_actions, run_batch

NUM_OVERLAPPING = BATCH // 2
SLOP = PARAMS.touch_distance  # [m] 0.005
PENETRATION_TOLERANCE = 1e-3  # [m] for resting contact under load
JUNK_ATOL = 1e-6
MOMENTUM_RTOL = 1e-4
ENERGY_GROWTH_PER_STEP = 0.01


@pytest.fixture(scope="module")
def fuzz():
    rng = np.random.default_rng(2024)
    states = [random_scene(rng, overlapping=i < NUM_OVERLAPPING) for i in range(BATCH)]
    motors, thrusters = random_actions(rng, SIZE_M, batch=BATCH)
    final, traj = run_batch(states, motors, thrusters)
    return dict(
        states=states,
        initial=to_numpy(stack(*states)),
        motors=motors,
        thrusters=thrusters,
        final=final,
        traj=traj,
    )


def test_fuzz_scenes_are_rich(fuzz):
    """Guard on the generator: the batch has joints, thrusters, statics, contacts, and things move."""
    initial, traj = fuzz["initial"], fuzz["traj"]
    assert initial.joints.active.sum() >= BATCH // 2
    assert initial.thrusters.active.sum() >= BATCH // 2
    extra_static = initial.bodies.active[:, SIZE_M.num_reserved_static :] & (
        initial.bodies.inverse_mass[:, SIZE_M.num_reserved_static :] == 0
    )
    assert extra_static.sum() >= 2
    assert traj.info.touching.any(axis=(1, 2)).sum() >= BATCH // 2
    overlap = traj.info.separation[:NUM_OVERLAPPING, 0] < -2 * SLOP
    assert overlap.any(-1).sum() >= NUM_OVERLAPPING // 2, "the overlapping half should start with deep overlaps"
    assert np.abs(traj.bodies.position[:, -1] - initial.bodies.position).max() > 0.5


def test_no_nan_or_inf_in_state(fuzz):
    bad = []
    for path, leaf in jax.tree_util.tree_leaves_with_path((fuzz["final"], fuzz["traj"].bodies, fuzz["traj"].joints)):
        leaf = np.asarray(leaf)
        if np.issubdtype(leaf.dtype, np.floating) and not np.all(np.isfinite(leaf)):
            scenes = np.unique(np.nonzero(~np.isfinite(leaf))[0])
            bad.append(f"{jax.tree_util.keystr(path)} in scenes {scenes.tolist()}")
    assert not bad, bad


def test_step_info_has_no_nan_or_negative_infinity(fuzz):
    """StepInfo.separation is finite or +inf ("no contact points"); NaN or -inf (infinitely deep) would poison
    any reduction over pairs. Pairs with an inactive slot have no contact points."""
    separation = fuzz["traj"].info.separation
    layout = pair_layout(SIZE_M)
    active = fuzz["initial"].bodies.active
    pair_active = np.broadcast_to((active[:, layout.body_a] & active[:, layout.body_b])[:, None, :], separation.shape)
    problems = []
    for name, mask in (("NaN", np.isnan(separation)), ("-inf", np.isneginf(separation))):
        if mask.any():
            problems.append(
                f"{name}: {mask.sum()} of {mask.size} pair-steps "
                f"({(mask & pair_active).sum()} with both bodies active, "
                f"{(mask & ~pair_active).sum()} with an inactive slot)"
            )
    assert not problems, problems
    assert not np.any(np.asarray(fuzz["traj"].info.touching) & ~pair_active), (
        "pairs with an inactive slot reported touching"
    )


def test_static_bodies_bitwise_unchanged(fuzz):
    initial, traj = fuzz["initial"].bodies, fuzz["traj"].bodies
    static = initial.active & (initial.inverse_mass == 0)
    assert static[:, : SIZE_M.num_reserved_static].all()
    for field in ("position", "rotation", "velocity", "angular_velocity"):
        start = np.asarray(getattr(initial, field))[:, None]
        got = np.asarray(getattr(traj, field))
        changed = (got != start).reshape(got.shape[:3] + (-1,)).any(-1) & static[:, None, :]
        assert not changed.any(), f"static {field} changed: (scene, step, body) {np.argwhere(changed)[:5].tolist()}"


def test_shape_data_never_changes(fuzz):
    initial, traj = fuzz["initial"].bodies, fuzz["traj"].bodies
    for field in (
        "inverse_mass",
        "inverse_inertia",
        "friction",
        "restitution",
        "collision_mode",
        "active",
        "n_vertices",
        "vertices",
        "radius",
    ):
        start = np.asarray(getattr(initial, field))[:, None]
        np.testing.assert_array_equal(
            np.asarray(getattr(traj, field)),
            np.broadcast_to(start, np.asarray(getattr(traj, field)).shape),
            err_msg=field,
        )


def test_state_within_clips(fuzz):
    b = fuzz["traj"].bodies
    assert np.abs(b.position).max() <= PARAMS.max_position
    assert np.abs(b.velocity).max() <= PARAMS.max_velocity
    assert np.abs(b.angular_velocity).max() <= PARAMS.max_angular_velocity


# --------------------------------------------------------------------------- inactive junk
def _with_junk(state, rng):
    """Fill every inactive body, joint and thruster slot (and their contact cache rows) with random finite data."""
    n, p = SIZE_M.num_bodies, SIZE_M.num_polygons
    b, j, t = state.bodies, state.joints, state.thrusters
    off = ~np.asarray(b.active)
    box = lambda w, h: np.array([[-w, -h], [w, -h], [w, h], [-w, h]]) / 2  # noqa: E731
    vertices = np.stack([box(*rng.uniform(0.1, 1.0, 2)) for _ in range(n)])
    is_polygon = np.arange(n) < p

    def fill(x, values, mask):
        x = np.array(x)
        values = np.asarray(values).astype(x.dtype)
        x[mask] = values[mask]
        return jnp.asarray(x)

    bodies = b.replace(
        position=fill(b.position, rng.uniform(0.0, 5.0, (n, 2)), off),
        rotation=fill(b.rotation, rng.uniform(-3, 3, n), off),
        velocity=fill(b.velocity, rng.uniform(-5, 5, (n, 2)), off),
        angular_velocity=fill(b.angular_velocity, rng.uniform(-5, 5, n), off),
        inverse_mass=fill(b.inverse_mass, rng.uniform(0.5, 2.0, n), off),
        inverse_inertia=fill(b.inverse_inertia, rng.uniform(0.5, 20.0, n), off),
        friction=fill(b.friction, rng.uniform(0, 1, n), off),
        restitution=fill(b.restitution, rng.uniform(0, 1, n), off),
        collision_mode=fill(b.collision_mode, rng.integers(0, 3, n), off),
        n_vertices=fill(b.n_vertices, np.where(is_polygon, 4, 0), off),
        vertices=fill(b.vertices, np.where(is_polygon[:, None, None], vertices, 0.0), off),
        radius=fill(b.radius, np.where(is_polygon, 0.0, rng.uniform(0.1, 0.5, n)), off),
    )
    nj, nt = SIZE_M.num_joints, SIZE_M.num_thrusters
    j_off, t_off = ~np.asarray(j.active), ~np.asarray(t.active)
    joints = j.replace(
        body_a=fill(j.body_a, rng.integers(0, n, nj), j_off),
        body_b=fill(j.body_b, rng.integers(0, n, nj), j_off),
        anchor_a=fill(j.anchor_a, rng.uniform(-1, 1, (nj, 2)), j_off),
        anchor_b=fill(j.anchor_b, rng.uniform(-1, 1, (nj, 2)), j_off),
        reference_angle=fill(j.reference_angle, rng.uniform(-1, 1, nj), j_off),
        is_fixed=fill(j.is_fixed, rng.random(nj) < 0.5, j_off),
        motor_on=fill(j.motor_on, np.ones(nj, bool), j_off),
        motor_speed=fill(j.motor_speed, rng.uniform(-3, 3, nj), j_off),
        motor_power=fill(j.motor_power, rng.uniform(0, 3, nj), j_off),
        has_limits=fill(j.has_limits, np.ones(nj, bool), j_off),
        lower_angle=fill(j.lower_angle, -rng.uniform(0, 1, nj), j_off),
        upper_angle=fill(j.upper_angle, rng.uniform(0, 1, nj), j_off),
        linear_impulse=fill(j.linear_impulse, rng.uniform(-1, 1, (nj, 2)), j_off),
        angular_impulse=fill(j.angular_impulse, rng.uniform(-1, 1, nj), j_off),
        motor_impulse=fill(j.motor_impulse, rng.uniform(-1, 1, nj), j_off),
        limit_impulse=fill(j.limit_impulse, rng.uniform(0, 1, (nj, 2)), j_off),
    )
    thrusters = t.replace(
        body=fill(t.body, rng.integers(0, n, nt), t_off),
        anchor=fill(t.anchor, rng.uniform(-0.5, 0.5, (nt, 2)), t_off),
        angle=fill(t.angle, rng.uniform(-3, 3, nt), t_off),
        power=fill(t.power, rng.uniform(0.5, 3, nt), t_off),
    )
    layout = pair_layout(SIZE_M)
    k = layout.num_pairs
    pair_off = off[layout.body_a] | off[layout.body_b]
    c = state.contacts
    contacts = c.replace(
        normal_impulse=fill(c.normal_impulse, rng.uniform(0, 1, (k, 2)), pair_off),
        tangent_impulse=fill(c.tangent_impulse, rng.uniform(-1, 1, (k, 2)), pair_off),
        feature=fill(c.feature, rng.integers(0, 12, (k, 2)), pair_off),
    )
    return state.replace(bodies=bodies, joints=joints, thrusters=thrusters, contacts=contacts)


def test_inactive_junk_changes_nothing(fuzz):
    rng = np.random.default_rng(99)
    junk_states = [_with_junk(s, rng) for s in fuzz["states"]]
    _, junk_traj = run_batch(junk_states, fuzz["motors"], fuzz["thrusters"])
    initial, traj = fuzz["initial"], fuzz["traj"]
    active = initial.bodies.active  # (B, N)
    failures = []
    for field in ("position", "rotation", "velocity", "angular_velocity"):
        clean, junk = np.asarray(getattr(traj.bodies, field)), np.asarray(getattr(junk_traj.bodies, field))
        diff = np.abs(clean - junk).reshape(clean.shape[:3] + (-1,)).max(-1)  # (B, K, N)
        diff = np.where(active[:, None, :], diff, 0.0)
        if diff.max() > JUNK_ATOL:
            scene, step, body = np.unravel_index(np.argmax(diff), diff.shape)
            failures.append(f"{field}: max diff {diff.max():.3g} (scene {scene}, step {step + 1}, body {body})")
    joint_active = initial.joints.active[:, None, :]
    for field in ("linear_impulse", "motor_impulse", "limit_impulse", "angular_impulse"):
        clean, junk = np.asarray(getattr(traj.joints, field)), np.asarray(getattr(junk_traj.joints, field))
        diff = np.abs(clean - junk).reshape(clean.shape[:3] + (-1,)).max(-1)
        diff = np.where(joint_active, diff, 0.0)
        if diff.max() > JUNK_ATOL:
            failures.append(f"joints.{field}: max diff {diff.max():.3g}")
    layout = pair_layout(SIZE_M)
    pair_active = (active[:, layout.body_a] & active[:, layout.body_b])[:, None, :]
    if np.any((traj.info.touching != junk_traj.info.touching) & pair_active):
        failures.append("info.touching differs for active pairs")
    sep_clean, sep_junk = traj.info.separation, junk_traj.info.separation
    if np.any((np.isfinite(sep_junk) != np.isfinite(sep_clean)) & pair_active):
        failures.append("info.separation finiteness differs for active pairs")
    finite = np.isfinite(sep_clean) & np.isfinite(sep_junk) & pair_active
    sep_diff = np.abs(np.where(finite, sep_clean, 0.0) - np.where(finite, sep_junk, 0.0)).max()
    if sep_diff > JUNK_ATOL:
        failures.append(f"info.separation: max diff {sep_diff:.3g}")
    # Junk bodies themselves stay where they were put.
    junk_initial = to_numpy(stack(*junk_states)).bodies
    for field in ("position", "velocity"):
        start = np.asarray(getattr(junk_initial, field))[:, None]
        moved = (np.asarray(getattr(junk_traj.bodies, field)) != start).any(-1) & ~active[:, None, :]
        if moved.any():
            failures.append(f"inactive junk {field} changed")
    assert not failures, failures


# --------------------------------------------------------------------------- penetration
def test_penetration_bounded_after_first_contact(fuzz):
    """Scenes that start separated: each collidable pair's separation at the start of step j >= 2 is at least
    -(max(2 slop, v dt) + tolerance), v bounding the pair's relative point speed during step j - 1, unless the
    pair was already that deep a step earlier and is being pushed out (penetration not growing)."""
    initial, traj = fuzz["initial"], fuzz["traj"]
    scenes = np.arange(NUM_OVERLAPPING, BATCH)
    layout = pair_layout(SIZE_M)
    a, b = layout.body_a, layout.body_b
    bodies = initial.bodies
    enabled = (
        bodies.active[:, a]
        & bodies.active[:, b]
        & np.asarray(modes_collide(bodies.collision_mode[:, a], bodies.collision_mode[:, b]))
        & initial.collision_matrix[:, a, b]
        & ~((bodies.inverse_mass[:, a] == 0) & (bodies.inverse_mass[:, b] == 0))
    )[scenes]  # (S, K)
    radius = bounding_radius(bodies)[scenes]  # (S, N)

    def point_speed(v, w):  # (S, K, N, ...) -> relative speed bound per pair, (S, K', pairs)
        return (
            np.linalg.norm(v[..., a, :] - v[..., b, :], axis=-1)
            + np.abs(w[..., a]) * radius[:, None, a]
            + np.abs(w[..., b]) * radius[:, None, b]
        )

    v = np.concatenate([bodies.velocity[scenes, None], traj.bodies.velocity[scenes]], 1).astype(np.float64)  # S_0..S_K
    w = np.concatenate([bodies.angular_velocity[scenes, None], traj.bodies.angular_velocity[scenes]], 1).astype(
        np.float64
    )
    speed = point_speed(v, w)  # (S, K + 1, pairs): speed of state S_i
    # info of step j (index j - 1) measures state S_{j-1}, produced by step j - 1 from S_{j-2}.
    separation = traj.info.separation[scenes, 1:]  # steps j = 2..K -> states S_1..S_{K-1}
    step_speed = np.maximum(speed[:, :-2], speed[:, 1:-1])  # max(S_{j-2}, S_{j-1})
    allowed = np.maximum(2 * SLOP, step_speed * PARAMS.dt) + PENETRATION_TOLERANCE
    previous = traj.info.separation[scenes, :-1]  # S_{j-2}
    deepening = separation < previous
    violation = (separation < -allowed) & deepening & enabled[:, None, :]
    if violation.any():
        excess = np.where(violation, -separation - allowed, 0.0)
        s, k, pair = np.unravel_index(np.argmax(excess), excess.shape)
        pytest.fail(
            f"{violation.sum()} pair-steps over the bound in {len(np.unique(np.nonzero(violation)[0]))} scenes; worst: "
            f"scene {scenes[s]}, step {k + 2}, pair {a[pair]}-{b[pair]}: separation {separation[s, k, pair]:.4f} m, "
            f"allowed -{allowed[s, k, pair]:.4f} m (relative speed {step_speed[s, k, pair]:.3f} m/s)"
        )


# --------------------------------------------------------------------------- zero gravity, no statics
def _zero_g_scene(rng):
    """Two boxes and three circles (no boundaries, no statics), apart, moving towards a common centre."""
    builder = SceneBuilder(SIZE_M, boundaries=False)
    placed = []
    shapes = [("box", rng.uniform(0.2, 0.5, 2)) for _ in range(2)] + [
        ("circle", rng.uniform(0.1, 0.3)) for _ in range(3)
    ]
    centre = np.array([2.5, 2.5])
    for kind, size in shapes:
        radius = float(np.linalg.norm(size) / 2) if kind == "box" else float(size)
        while True:
            pos = centre + rng.uniform(-1.0, 1.0, 2)
            if all(np.linalg.norm(pos - q) > radius + r + 0.05 for q, r in placed):
                break
        placed.append((pos, radius))
        velocity = (centre - pos) * rng.uniform(1.0, 3.0) + rng.uniform(-0.5, 0.5, 2)
        kw = dict(
            velocity=tuple(velocity),
            angular_velocity=float(rng.uniform(-2, 2)),
            density=float(rng.uniform(0.5, 3.0)),
            friction=float(rng.uniform(0.0, 1.0)),
            restitution=0.0,
        )
        if kind == "box":
            builder.add_box(pos, tuple(size), rotation=float(rng.uniform(-np.pi, np.pi)), **kw)
        else:
            builder.add_circle(pos, float(size), **kw)
    return builder.build().replace(gravity=jnp.zeros(2))


@pytest.fixture(scope="module")
def zero_g():
    rng = np.random.default_rng(5)
    states = [_zero_g_scene(rng) for _ in range(8)]
    _, traj = run_batch(states)
    initial = to_numpy(stack(*states))
    assert not (initial.bodies.active & (initial.bodies.inverse_mass == 0)).any(), "no static bodies"
    mass, inertia = masses(initial.bodies)
    return dict(initial=initial, traj=traj, mass=mass, inertia=inertia)


def test_zero_g_scenes_collide(zero_g):
    assert zero_g["traj"].info.touching.any(axis=(1, 2)).all()


def test_linear_momentum_conserved_in_zero_gravity(zero_g):
    initial, traj, mass = zero_g["initial"], zero_g["traj"], zero_g["mass"]
    v0 = initial.bodies.velocity.astype(np.float64)
    p0 = np.sum(mass[..., None] * v0, axis=1)  # (S, 2)
    scale = np.sum(mass * np.linalg.norm(v0, axis=-1), axis=1)  # (S,)
    p = np.sum(mass[:, None, :, None] * traj.bodies.velocity.astype(np.float64), axis=2)  # (S, K, 2)
    error = np.linalg.norm(p - p0[:, None], axis=-1) / scale[:, None]
    assert error.max() <= MOMENTUM_RTOL, f"relative momentum error {error.max():.3g} (scene {np.argmax(error.max(1))})"


def test_kinetic_energy_does_not_increase_in_zero_gravity(zero_g):
    initial, traj, mass, inertia = zero_g["initial"], zero_g["traj"], zero_g["mass"], zero_g["inertia"]
    energy = np.concatenate(
        [
            kinetic_energy(initial.bodies, mass, inertia)[:, None],
            kinetic_energy(traj.bodies, mass[:, None], inertia[:, None]),
        ],
        1,
    )  # (S, K + 1)
    growth = energy[:, 1:] / np.maximum(energy[:, :-1], 1e-12)
    scene, step = np.unravel_index(np.argmax(growth), growth.shape)
    assert growth.max() <= 1.0 + ENERGY_GROWTH_PER_STEP, (
        f"kinetic energy grew by {100 * (growth.max() - 1):.2f} % in one step (scene {scene}, step {step + 1})"
    )
    assert np.all(energy[:, -1] <= energy[:, 0] * (1 + ENERGY_GROWTH_PER_STEP))
