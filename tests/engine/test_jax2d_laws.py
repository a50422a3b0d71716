"""Jax2D's joint law and contact order (`JointLaw.JAX2D`, `ContactOrder.JAX2D`, both in the kinetix scheme): what
Jax2D's solver does, checked against hand-derived values and invariants. How closely the scheme then plays as
Kinetix is measured by benchmarks/fidelity_paired.py (docs/fidelity.md)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from engine_test_helpers import FLOOR_TOP, SIZE_L, SIZE_S, zero_gravity

from kforge.engine import SceneBuilder, SimParams, physics_scheme
from kforge.engine.jax2d_contacts import solver_batches
from kforge.engine.pairs import pair_layout
from tests.rollouts import run_scene

KINETIX = physics_scheme("kinetix")
JOINT_STIFFNESS, JOINT_VELOCITY_BIAS, JOINT_POSITION_SHARE = 0.6, 2.0, 0.7
"""Jax2D's joint constants in Kinetix (`joint_stiffness`, `baumgarte_coefficient_joints_v` [1/s],
`baumgarte_coefficient_joints_p`)."""


def _two_discs_joined_with_a_gap(gap: float):
    """Two discs of different mass at rest in zero gravity, joined by a revolute joint at the midpoint of their
    centres, then disc b moved `gap` [m] further along x: (state, disc a, disc b)."""
    builder = SceneBuilder(SIZE_S)
    a = builder.add_circle((2.0, 3.0), 0.2)
    b = builder.add_circle((2.6, 3.0), 0.35)
    builder.add_revolute_joint(a, b, (2.3, 3.0))
    state = zero_gravity(builder.build())
    moved = state.bodies.position.at[b, 0].add(gap)
    return state.replace(bodies=state.bodies.replace(position=moved)), a, b


def test_one_pass_of_jax2ds_joint_moves_both_bodies_and_pushes_them_together_by_its_shares():
    """Bodies at rest: the anchors' relative velocity is zero, so the impulse is JOINT_STIFFNESS x JOINT_VELOCITY_BIAS
    x gap / (m_a^-1 + m_b^-1), along the gap (no turn: the levers lie along it), and the pass moves each body by
    JOINT_POSITION_SHARE of the gap in proportion to its inverse mass. After the pass positions advance by v dt."""
    gap = 0.01
    state, a, b = _two_discs_joined_with_a_gap(gap)
    inverse_mass = np.asarray(state.bodies.inverse_mass)[[a, b]]
    start_x = np.asarray(state.bodies.position)[[a, b], 0]
    one_pass = dataclasses.replace(KINETIX.static(SIZE_S), num_iterations=1)
    params = KINETIX.sim(SimParams())
    _, trajectory = run_scene(state, one_pass, 1, params=params)
    impulse = JOINT_STIFFNESS * JOINT_VELOCITY_BIAS * gap / inverse_mass.sum()
    velocity = np.array([inverse_mass[0], -inverse_mass[1]]) * impulse
    moved = np.array([1.0, -1.0]) * JOINT_POSITION_SHARE * gap * inverse_mass / inverse_mass.sum()
    np.testing.assert_allclose(trajectory.velocity[1, [a, b], 0], velocity, rtol=1e-5)
    np.testing.assert_allclose(trajectory.position[1, [a, b], 0], start_x + moved + params.dt * velocity, rtol=1e-6)
    np.testing.assert_allclose(trajectory.angular_velocity[1, [a, b]], 0.0, atol=1e-6)


def test_jax2ds_joint_keeps_the_momentum_and_the_centre_of_mass_of_a_free_pair():
    """Every impulse and every position move of the law acts on the two bodies in opposite directions, weighted by
    their inverse masses: a spinning, drifting jointed pair in zero gravity keeps its momentum, and its centre of
    mass moves in a straight line at constant speed."""
    state, a, b = _two_discs_joined_with_a_gap(0.02)
    velocity = state.bodies.velocity.at[a].set(np.array([0.3, -0.2])).at[b].set(np.array([-0.1, 0.4]))
    spin = state.bodies.angular_velocity.at[a].set(3.0)
    state = state.replace(bodies=state.bodies.replace(velocity=velocity, angular_velocity=spin))
    mass = 1.0 / np.asarray(state.bodies.inverse_mass)[[a, b]]
    steps = 60
    final, trajectory = run_scene(state, KINETIX.static(SIZE_S), steps, params=KINETIX.sim(SimParams()))
    momentum = np.einsum("b,tbk->tk", mass, trajectory.velocity[:, [a, b]])
    np.testing.assert_allclose(momentum, np.broadcast_to(momentum[0], momentum.shape), atol=1e-5)
    centre = np.einsum("b,tbk->tk", mass, trajectory.position[:, [a, b]]) / mass.sum()
    expected = centre[0] + np.arange(steps + 1)[:, None] * SimParams().dt * momentum[0] / mass.sum()
    np.testing.assert_allclose(centre, expected, atol=1e-5)

    def anchor(body, local):
        angle = float(trajectory.rotation[-1, body])
        turn = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
        return trajectory.position[-1, body] + turn @ np.asarray(local)

    joints = final.joints
    apart = anchor(a, joints.anchor_a[0]) - anchor(b, joints.anchor_b[0])
    assert np.linalg.norm(apart) < 5e-3  # the joint held


def test_pairs_are_dealt_to_batches_as_jax2d_sorts_them():
    """Jax2D sorts a kind's pairs by whether they touch (stably: untouching first, each group in pair order) and
    deals the sorted list out to ceil(n / 16) batches in turn (16: Kinetix's solver_batch_size). Size l has 60
    polygon-polygon pairs (4 batches) and 48 circle-polygon pairs (3 batches)."""
    layout = pair_layout(KINETIX.static(SIZE_L))
    rng = np.random.default_rng(3)
    counted = rng.random(layout.num_pairs) < 0.3
    batches = np.asarray(solver_batches(counted, layout))
    for colour, slots in enumerate(layout.colour_slots):
        real = slots[slots < layout.num_pairs]
        count = -(-len(real) // 16)
        order = np.argsort(counted[real], kind="stable")
        expected = np.empty(len(real), int)
        expected[order] = np.arange(len(real)) % count
        np.testing.assert_array_equal(batches[colour, : len(real)], expected)
    assert [-(-int((s < layout.num_pairs).sum()) // 16) for s in layout.colour_slots] == [4, 3, 1]


def test_the_last_pair_of_a_padded_kind_keeps_no_impulse_and_the_others_keep_theirs():
    """Jax2D's padding writes over the accumulated impulse of a kind's last pair: two discs resting on each other on
    the floor (size s has one circle-circle pair, so it is the last of its kind) carry no impulse from step to step,
    while the lower disc's contact with the floor keeps its weight's impulse."""
    builder = SceneBuilder(SIZE_S)
    radius = 0.3
    lower = builder.add_circle((2.5, FLOOR_TOP + radius), radius)
    upper = builder.add_circle((2.5, FLOOR_TOP + 3 * radius), radius)
    state, _ = run_scene(builder.build(), KINETIX.static(SIZE_S), 120, params=KINETIX.sim(SimParams()))
    layout = pair_layout(KINETIX.static(SIZE_S))
    pairs = list(zip(layout.body_a.tolist(), layout.body_b.tolist(), strict=True))
    normal = np.asarray(state.contacts.normal_impulse)
    assert normal[pairs.index((lower, upper))].max() == 0.0
    assert normal[pairs.index((0, lower))].max() > 0.0
    position = np.asarray(state.bodies.position)
    assert position[upper, 1] - position[lower, 1] == pytest.approx(2 * radius, abs=0.02)  # still stacked


def test_the_step_starts_with_gravity_then_thrust_in_jax2ds_arithmetic():
    """Jax2D adds g dt to a body's velocity, then each thruster's impulse inverse mass x direction x (power x base
    power x action x dt), and turns it by inverse inertia x (lever x direction) x the same; a box in free flight
    with a thruster off its centre has, after one step, exactly those float32 velocities."""
    builder = SceneBuilder(SIZE_S)
    box = builder.add_box((2.5, 3.0), (0.6, 0.2), rotation=0.3)
    angle, power = 1.1, 1.7
    builder.add_thruster(box, (2.6, 3.05), angle, power=power)
    state = builder.build()
    params = KINETIX.sim(SimParams())
    _, trajectory = run_scene(state, KINETIX.static(SIZE_S), 1, params=params, thrust=np.ones(1, np.float32))
    f32 = np.float32
    bodies, thruster = state.bodies, state.thrusters
    rotation = f32(bodies.rotation[box])
    turn = f32(thruster.angle[0]) + rotation
    direction = np.array([np.cos(turn), np.sin(turn)], f32)
    anchor = np.asarray(thruster.anchor[0], f32)
    lever = np.array(
        [
            np.cos(rotation) * anchor[0] - np.sin(rotation) * anchor[1],
            np.sin(rotation) * anchor[0] + np.cos(rotation) * anchor[1],
        ],
        f32,
    )
    dt = f32(params.dt)
    force = f32(power) * f32(1.0) * f32(params.base_thruster_power) * f32(1.0) * dt
    velocity = np.asarray(state.gravity, f32) * dt + f32(bodies.inverse_mass[box]) * direction * force
    spin = f32(bodies.inverse_inertia[box]) * (lever[0] * direction[1] - lever[1] * direction[0]) * force
    np.testing.assert_allclose(trajectory.velocity[1, box], velocity, rtol=2e-7)
    assert trajectory.angular_velocity[1, box] == pytest.approx(spin, rel=2e-6)
