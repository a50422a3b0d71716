"""Test group D of the engine test plan (docs/physics.md): joints, motors and limits, at the plan's
pass thresholds. Every scene uses the `l` size (6 joints), so this module compiles one runner.

Every test prints a `MEASURED` line (run pytest with -s to see them).
"""

from __future__ import annotations

import dataclasses
import math

import jax.numpy as jnp
import numpy as np
import pytest
from engine_test_helpers import SIZE_L, SIZE_S, G, crossings, elliptic_k, joint_anchor_error, masses, rotate

from kforge.engine import ContactLaw, MotorLaw, SceneBuilder, SimParams
from kforge.engine.params import JointLaw
from tests.helpers import measured
from tests.rollouts import run_scene

STATIC = SIZE_L
PARAMS = SimParams()
CONSTRAINT_MOTORS = dataclasses.replace(STATIC, motor_law=MotorLaw.CONSTRAINT)
"""The motor as a constraint row (not Kinetix's law; kept as an option)."""
DT = PARAMS.dt
SUBSTEP = DT / STATIC.num_substeps
PIVOT = np.array([5.0, 4.0])


def _builder_with_pivot(static=STATIC) -> SceneBuilder:
    """No boundaries; a small static box at PIVOT in reserved polygon slot 0 (body 0)."""
    builder = SceneBuilder(static, boundaries=False)
    builder.add_box(PIVOT, (0.1, 0.1), static=True, slot=0)
    return builder


def _joint_angle(traj, state, joint: int) -> np.ndarray:
    j = state.joints
    a, b = int(j.body_a[joint]), int(j.body_b[joint])
    return traj.rotation[:, b] - traj.rotation[:, a] - float(j.reference_angle[joint])


def _motor_bound(state, joint: int) -> float:
    """[N m s] largest motor impulse of one substep: motor_power * base_motor_power * axial inertia * h."""
    j, b = state.joints, state.bodies
    inverse_sum = float(b.inverse_inertia[int(j.body_a[joint])]) + float(b.inverse_inertia[int(j.body_b[joint])])
    return float(j.motor_power[joint]) * PARAMS.base_motor_power / inverse_sum * SUBSTEP


# =========================================================================== pendulums
LENGTH, BOB_RADIUS = 1.0, 0.05


def _pendulum(theta0: float, seconds: float = 10.0):
    """Small disc on a 1 m massless arm (revolute joint to a static pivot), released at rest from `theta0`."""
    builder = _builder_with_pivot()
    bob = builder.add_circle(PIVOT + LENGTH * np.array([math.sin(theta0), -math.cos(theta0)]), BOB_RADIUS)
    builder.add_revolute_joint(0, bob, PIVOT)
    state = builder.build()
    _, traj = run_scene(state, STATIC, int(round(seconds / DT)))
    arm = traj.position[:, bob] - PIVOT
    theta = np.arctan2(arm[:, 0], -arm[:, 1])
    # Period from all zero crossings (two per period): slope of crossing time vs crossing index, doubled.
    times = np.sort(np.concatenate([crossings(theta, DT, 1), crossings(theta, DT, -1)]))
    period = 2.0 * np.polyfit(np.arange(len(times)), times, 1)[0]
    # Compound pendulum: I_pivot / (m g L) with I_pivot = m r^2 / 2 + m L^2 (the mass cancels).
    inertia_ratio = (0.5 * BOB_RADIUS**2 + LENGTH**2) / (G * LENGTH)
    return state, traj, theta, period, inertia_ratio


def test_pendulum_small_amplitude():
    theta0 = 0.1
    state, traj, theta, period, inertia_ratio = _pendulum(theta0)
    expected = 2.0 * math.pi * math.sqrt(inertia_ratio)
    anchor_error = joint_anchor_error(traj, state, 0).max()
    last_period = theta[-int(round(period / DT)) :]
    amplitude_loss = 1.0 - np.abs(last_period).max() / theta0
    measured(
        "pendulum 0.1 rad",
        period_s=period,
        expected_s=expected,
        period_rel_error=period / expected - 1,
        anchor_error_m=anchor_error,
        amplitude_loss_10s=amplitude_loss,
    )
    assert abs(period / expected - 1.0) <= 0.005
    assert anchor_error < 5e-3
    assert amplitude_loss < 0.05


def test_pendulum_large_amplitude_elliptic_period():
    theta0 = 1.5
    state, traj, theta, period, inertia_ratio = _pendulum(theta0)
    expected = 4.0 * math.sqrt(inertia_ratio) * elliptic_k(math.sin(theta0 / 2.0))
    measured(
        "pendulum 1.5 rad",
        period_s=period,
        expected_s=expected,
        period_rel_error=period / expected - 1,
        small_angle_period_s=2 * math.pi * math.sqrt(inertia_ratio),
        anchor_error_m=joint_anchor_error(traj, state, 0).max(),
    )
    assert abs(period / expected - 1.0) <= 0.01


def test_elliptic_integral_helper():
    assert abs(elliptic_k(0.0) - math.pi / 2) < 1e-12
    assert abs(elliptic_k(math.sin(math.pi / 4)) - 1.8540746773013719) < 1e-12


# =========================================================================== chains and mass ratios
@pytest.fixture(scope="module")
def chain_errors():
    """5 links (0.4 m x 0.1 m) hinged end to end from a static pivot, released horizontally, 10 s:
    (n+1,) largest anchor separation over the 5 joints at every step, and the lowest height of the last link."""
    builder = _builder_with_pivot()
    links = [builder.add_box(PIVOT + (0.2 + 0.4 * i, 0.0), (0.4, 0.1)) for i in range(5)]
    builder.add_revolute_joint(0, links[0], PIVOT)
    for i in range(1, 5):
        builder.add_revolute_joint(links[i - 1], links[i], PIVOT + (0.4 * i, 0.0))
    state = builder.build()
    _, traj = run_scene(state, STATIC, 600)
    errors = np.stack([joint_anchor_error(traj, state, j) for j in range(5)], -1).max(-1)
    lowest = traj.position[:, links[-1], 1].min()
    measured(
        "5-link chain",
        max_separation_m=errors.max(),
        final_separation_m=errors[-1],
        median_separation_m=np.median(errors),
        last_second_median_m=np.median(errors[-60:]),
        last_second_max_m=errors[-60:].max(),
        lowest_link_y=lowest,
    )
    assert lowest < PIVOT[1] - 1.5  # it really fell and swung
    return errors


def test_five_link_chain_max_separation(chain_errors):
    assert chain_errors.max() < 0.015


def test_five_link_chain_final_separation(chain_errors):
    """Separation at the end of the 10 s run (the chain is still swinging)."""
    assert chain_errors[-1] < 1e-3


def test_mass_ratio_100_to_1_across_a_joint():
    builder = _builder_with_pivot()
    light = builder.add_box(PIVOT + (0.2, 0.0), (0.4, 0.1), density=1.0)
    heavy = builder.add_box(PIVOT + (0.6, 0.0), (0.4, 0.1), density=100.0)
    builder.add_revolute_joint(0, light, PIVOT)
    builder.add_revolute_joint(light, heavy, PIVOT + (0.4, 0.0))
    state = builder.build()
    inverse_mass = np.asarray(state.bodies.inverse_mass)
    assert abs(inverse_mass[light] / inverse_mass[heavy] - 100.0) < 1e-3
    _, traj = run_scene(state, STATIC, 300)
    errors = np.stack([joint_anchor_error(traj, state, j) for j in range(2)], -1)
    measured(
        "mass ratio 100:1",
        max_error_m=errors.max(),
        max_error_per_joint_m=errors.max(0).round(5).tolist(),
        final_error_m=errors[-1].max(),
    )
    assert errors.max() < 0.02


# =========================================================================== fixed joints
def test_fixed_joint_cantilever_holds_relative_angle():
    """A beam welded at a rotated static wall, with a heavy rotated block welded at its tip."""
    builder = SceneBuilder(STATIC, boundaries=False)
    wall_angle, beam_angle, load_angle = 0.2, -0.3, 0.7
    wall = builder.add_box(PIVOT, (0.2, 1.0), rotation=wall_angle, static=True, slot=0)
    root = PIVOT + rotate(wall_angle, np.array([0.1, 0.0]))
    beam_dir = rotate(beam_angle, np.array([1.0, 0.0]))
    beam = builder.add_box(root + 0.5 * beam_dir, (1.0, 0.1), rotation=beam_angle)
    tip = root + beam_dir
    load = builder.add_box(
        tip + rotate(load_angle, np.array([0.1, 0.0])), (0.2, 0.2), rotation=load_angle, density=10.0
    )
    builder.add_fixed_joint(wall, beam, root)
    builder.add_fixed_joint(beam, load, tip)
    state = builder.build()
    _, traj = run_scene(state, STATIC, 300)
    angle_errors = np.stack([np.abs(_joint_angle(traj, state, j)) for j in range(2)], -1)
    anchor_errors = np.stack([joint_anchor_error(traj, state, j) for j in range(2)], -1)
    tip_drop = traj.position[0, load, 1] - traj.position[:, load, 1]
    measured(
        "fixed-joint cantilever",
        max_angle_error_rad=angle_errors.max(),
        per_joint=angle_errors.max(0).round(5).tolist(),
        final_angle_error_rad=angle_errors[-1].max(),
        max_anchor_error_m=anchor_errors.max(),
        max_tip_drop_m=tip_drop.max(),
    )
    assert angle_errors.max() < 0.01


# =========================================================================== limits and motors
def test_revolute_limits_under_gravity_and_release():
    """Two bars hinged at a static pivot (one pointing +x, one -x), limits +-0.5 rad, released horizontally:
    they swing onto the lower and upper limits; then motors drive each back through the range onto the other limit."""
    builder = _builder_with_pivot()
    right = builder.add_box(PIVOT + (0.25, 0.0), (0.5, 0.05))
    left = builder.add_box(PIVOT - (0.25, 0.0), (0.5, 0.05))
    for bar in (right, left):
        builder.add_revolute_joint(0, bar, PIVOT, motor_speed=1.0, motor_power=1.0, motor_on=False, limits=(-0.5, 0.5))
    state = builder.build()
    state, fall = run_scene(state, STATIC, 120)
    fall_right, fall_left = _joint_angle(fall, state, 0), _joint_angle(fall, state, 1)
    overshoot_fall = max(-0.5 - fall_right.min(), fall_left.max() - 0.5)
    # Drive away from the limits: motors on, the right bar up (positive), the left bar down (negative).
    motor_on = np.zeros(STATIC.num_joints, bool)
    motor_on[:2] = True
    state = state.replace(joints=state.joints.replace(motor_on=jnp.asarray(motor_on)))
    actions = np.zeros(STATIC.num_joints, np.float32)
    actions[:2] = (1.0, -1.0)
    _, drive = run_scene(state, STATIC, 120, motor=actions)
    drive_right, drive_left = _joint_angle(drive, state, 0), _joint_angle(drive, state, 1)
    released_after = int(np.flatnonzero((drive_right > 0.0) & (drive_left < 0.0))[0])
    overshoot_drive = max(drive_right.max() - 0.5, -0.5 - drive_left.min())
    measured(
        "revolute limits",
        fall_min_right_rad=fall_right.min(),
        fall_max_left_rad=fall_left.max(),
        overshoot_fall_rad=overshoot_fall,
        rest_right_rad=fall_right[-1],
        rest_left_rad=fall_left[-1],
        steps_to_cross_zero=released_after,
        drive_end_right_rad=drive_right[-1],
        drive_end_left_rad=drive_left[-1],
        overshoot_drive_rad=overshoot_drive,
    )
    assert fall_right.min() < -0.45 and fall_left.max() > 0.45  # both reached their limit
    assert overshoot_fall < 0.05
    assert abs(fall_right[-1] + 0.5) < 0.05 and abs(fall_left[-1] - 0.5) < 0.05  # resting on the limits
    assert released_after <= 30  # the limits let go when driven inward
    assert overshoot_drive < 0.05
    assert abs(drive_right[-1] - 0.5) < 0.05 and abs(drive_left[-1] + 0.5) < 0.05  # now held at the other limits


def _wheel_spinning_towards_its_limit(static):
    """(state, wheel): a 0.2 m wheel pinned at its centre to a static box at PIVOT (body 0), limits +-0.5 rad,
    spinning at 2.7 rad/s towards the upper limit; no boundaries."""
    builder = _builder_with_pivot(static)
    wheel = builder.add_circle(PIVOT, 0.2)
    builder.add_revolute_joint(0, wheel, PIVOT, limits=(-0.5, 0.5))
    state = builder.build()
    spin = np.zeros(state.bodies.angular_velocity.shape, np.float32)
    spin[wheel] = 2.7
    return state.replace(bodies=state.bodies.replace(angular_velocity=jnp.asarray(spin))), wheel


def test_a_spinning_wheel_meets_its_angle_limit():
    """A wheel pinned at its centre (no gravity torque), limits +-0.5 rad, spinning at 2.7 rad/s (0.045 rad a step)
    towards the upper limit: the speculative limit rows stop it at the limit and hold it there."""
    state, wheel = _wheel_spinning_towards_its_limit(STATIC)
    _, traj = run_scene(state, STATIC, 30)
    angle, omega = _joint_angle(traj, state, 0), traj.angular_velocity[:, wheel]
    measured("wheel at its limit", max_angle_rad=angle.max(), final_omega=omega[-1])
    assert angle.max() < 0.5 + 1e-3
    assert abs(omega[-1]) < 1e-3


def test_relaxing_joints_only_holds_a_wheel_at_its_limit_where_no_relaxing_pass_lets_it_drift_back():
    """The spinning wheel above, under 4 substeps of 3 position-correcting passes and Jax2D's push-out for contacts.
    Without a relaxing pass the limit row's correction velocity stays in the wheel, which leaves its limit turning
    back; one relaxing pass of joints only (`relax_contacts=False`) takes it out, and the wheel rests at the limit."""
    state, wheel = _wheel_spinning_towards_its_limit(SIZE_S)  # the smallest size: two schemes to compile
    params = SimParams(speculative_distance=0.0, speculative_reach=0.0)
    scheme = dict(num_iterations=3, block_contacts=True, contact_law=ContactLaw.BAUMGARTE)
    final = {}
    for relax in (0, 1):
        static = dataclasses.replace(SIZE_S, num_relax_iterations=relax, relax_contacts=False, **scheme)
        _, traj = run_scene(state, static, 30, params=params)
        final[relax] = (_joint_angle(traj, state, 0).max(), traj.angular_velocity[-1, wheel])
    measured("wheel at its limit, joints relaxed or not", relaxed=final[1], not_relaxed=final[0])
    assert final[1][0] < 0.5 + 1e-3 and abs(final[1][1]) < 1e-3
    assert final[0][1] < -0.01


def test_a_wheel_started_past_its_limit_returns_as_each_joint_law_says():
    """A wheel at rest 1 rad past its upper limit (+-0.5 rad), no gravity torque. The soft joint law snaps it back
    within a step or two (the joint's softness); Jax2D's leaves it where it is, as Jax2D does: it only turns back a
    joint that turns further out."""
    builder = _builder_with_pivot()
    wheel = builder.add_circle(PIVOT, 0.2)
    builder.add_revolute_joint(0, wheel, PIVOT, limits=(-0.5, 0.5))
    state = builder.build()
    state = state.replace(bodies=state.bodies.replace(rotation=state.bodies.rotation.at[wheel].set(1.5)))
    excess = {}
    for law in (JointLaw.SOFT, JointLaw.JAX2D):
        _, traj = run_scene(state, dataclasses.replace(STATIC, joint_law=law), 90)
        excess[law] = _joint_angle(traj, state, 0) - 0.5
    measured(
        "wheel started past its limit",
        soft_after_2_steps=excess[JointLaw.SOFT][2],
        jax2d_after_90_steps=excess[JointLaw.JAX2D][90],
    )
    assert excess[JointLaw.SOFT][2] < 0.1
    np.testing.assert_allclose(excess[JointLaw.JAX2D], 1.0, atol=1e-6)


def _motor_wheel(motor_speed: float = 1.0, motor_power: float = 1.0):
    """A disc pinned at its centre to the static pivot by a motorised joint."""
    builder = _builder_with_pivot()
    wheel = builder.add_circle(PIVOT, 0.2)
    builder.add_revolute_joint(0, wheel, PIVOT, motor_speed=motor_speed, motor_power=motor_power, motor_on=True)
    return builder.build(), wheel


def _motor_actions(value: float = 1.0) -> np.ndarray:
    actions = np.zeros(STATIC.num_joints, np.float32)
    actions[0] = value
    return actions


@pytest.mark.parametrize("motor_speed", [0.4, 1.0, 3.0])
def test_servo_motor_free_wheel_follows_kinetix_recurrence(motor_speed):
    """Kinetix's servo on a free wheel: w' = w - base_power x power x dt x tanh(decay x (w - target)) exactly, as
    the wheel's own inertia is the axial inertia; it overshoots, then settles on the target."""
    state, wheel = _motor_wheel(motor_speed)
    _, traj = run_scene(state, STATIC, 60, motor=_motor_actions())
    target = motor_speed * PARAMS.base_motor_speed
    expected = [0.0]
    for _ in range(60):
        w = expected[-1]
        expected.append(w - PARAMS.base_motor_power * DT * math.tanh(PARAMS.motor_decay * (w - target)))
    omega = traj.angular_velocity[:, wheel]
    measured("servo motor free wheel", target=target, omega_steps_1_to_5=omega[1:6].round(4).tolist())
    np.testing.assert_allclose(omega, expected, rtol=1e-4, atol=1e-4)
    assert np.all(np.abs(omega[30:] / target - 1.0) < 0.01)
    assert np.all(traj.motor_impulse == 0.0)  # no constraint row, nothing to warm-start


def test_servo_motor_holds_a_bar_where_its_impulse_balances_gravity():
    """A 1 m bar hinged at its end to a static pivot, a weak servo motor driving it up: at rest the motor's angular
    impulse per step is base_power x power x dt x I x tanh(decay x target speed), so the bar hangs where that
    balances gravity's, m g (L / 2) cos(angle) dt."""
    length, height, power = 1.0, 0.1, 0.06
    builder = _builder_with_pivot()
    bar = builder.add_box(PIVOT + (length / 2, 0.0), (length, height))
    builder.add_revolute_joint(0, bar, PIVOT, motor_speed=1.0, motor_power=power, motor_on=True)
    state = builder.build()
    mass = 1.0 / float(state.bodies.inverse_mass[bar])
    inertia = 1.0 / float(state.bodies.inverse_inertia[bar])
    holding = PARAMS.base_motor_power * power * inertia * math.tanh(PARAMS.motor_decay * PARAMS.base_motor_speed)
    equilibrium = -math.acos(holding / (mass * G * length / 2))
    _, traj = run_scene(state, STATIC, 600, motor=_motor_actions())
    angle = _joint_angle(traj, state, 0)
    first, last = angle[1:121], angle[-120:]
    measured(
        "servo motor under load",
        mean_angle_last_2s=last.mean(),
        equilibrium=equilibrium,
        swing_first_2s=np.ptp(first),
        swing_last_2s=np.ptp(last),
    )
    assert abs(last.mean() - equilibrium) < 0.02
    assert np.ptp(last) < 0.5 * np.ptp(first)  # the servo damps the swing about the equilibrium


def test_constraint_motor_free_wheel_reaches_target_speed():
    state, wheel = _motor_wheel()
    _, traj = run_scene(state, CONSTRAINT_MOTORS, 100, motor=_motor_actions())
    target = 1.0 * PARAMS.base_motor_speed * 1.0
    omega = traj.angular_velocity[:, wheel]
    relative_error = np.abs(omega / target - 1.0)
    within = np.flatnonzero(relative_error >= 0.01)
    settled_after = int(within[-1]) + 1 if within.size else 0
    bound = _motor_bound(state, 0)
    measured(
        "motor free wheel",
        target_rad_s=target,
        omega_steps_1_to_5=omega[1:6].round(4).tolist(),
        settled_after_steps=settled_after,
        max_error_after_30=relative_error[30:].max(),
        max_impulse_over_bound=np.abs(traj.motor_impulse[:, 0]).max() / bound,
    )
    assert settled_after <= 30
    assert np.all(np.abs(traj.motor_impulse[:, 0]) <= bound * (1 + 1e-5))


@pytest.mark.parametrize("static", [STATIC, CONSTRAINT_MOTORS], ids=["servo", "constraint"])
def test_motor_with_zero_action_is_off_and_the_wheel_spins_freely(static):
    # Kinetix/Jax2D semantics: a motor acts only while its action is non-zero; action 0 is not a brake.
    builder = _builder_with_pivot()
    wheel = builder.add_circle(PIVOT, 0.2, angular_velocity=3.0)
    builder.add_revolute_joint(0, wheel, PIVOT, motor_speed=1.0, motor_power=1.0, motor_on=True)
    state = builder.build()
    _, traj = run_scene(state, static, 60, motor=np.zeros(STATIC.num_joints, np.float32))
    np.testing.assert_allclose(traj.angular_velocity[:, wheel], 3.0, rtol=1e-5)
    assert np.all(traj.motor_impulse[:, 0] == 0.0)


def test_constraint_motor_under_heavy_load_respects_and_saturates_torque_bound():
    """A 1 m bar hinged at its end; a weak motor (power 0.02) cannot lift it, so it stays saturated."""
    builder = _builder_with_pivot()
    bar = builder.add_box(PIVOT + (0.5, 0.0), (1.0, 0.1))
    builder.add_revolute_joint(0, bar, PIVOT, motor_speed=1.0, motor_power=0.02, motor_on=True)
    state = builder.build()
    bound = _motor_bound(state, 0)
    mass = 1.0 / float(state.bodies.inverse_mass[bar])
    assert bound / SUBSTEP < mass * G * 0.5  # the motor torque cannot hold the bar horizontal
    _, traj = run_scene(state, CONSTRAINT_MOTORS, 300, motor=_motor_actions())
    impulse = np.abs(traj.motor_impulse[:, 0])
    saturated = impulse >= bound * (1 - 1e-4)
    angle = _joint_angle(traj, state, 0)
    equilibrium = -math.acos(bound / SUBSTEP / (mass * G * 0.5))
    measured(
        "motor under load",
        bound_n_m_s=bound,
        max_impulse_over_bound=impulse.max() / bound,
        saturated_fraction=saturated.mean(),
        mean_angle_last_2s=angle[-120:].mean(),
        static_equilibrium_angle=equilibrium,
        max_speed=np.abs(traj.angular_velocity[:, bar]).max(),
    )
    assert np.all(impulse <= bound * (1 + 1e-5))
    assert saturated.mean() > 0.9


def test_servo_motors_on_a_shared_hub_conserve_angular_momentum():
    """Zero gravity, at rest: a free hub driven by two motorised wheels, the hub being body a of one joint and body
    b of the other. Joint and motor impulses are internal, so the total angular momentum stays 0 while the wheels
    spin up; a hub that missed one joint's servo impulse (an accumulation that drops or repeats an entry) would not."""
    builder = SceneBuilder(STATIC, boundaries=False)
    hub = builder.add_box(PIVOT, (1.0, 0.3))
    left = builder.add_circle(PIVOT - (0.4, 0.0), 0.15)
    right = builder.add_circle(PIVOT + (0.4, 0.0), 0.25)
    builder.add_revolute_joint(hub, left, PIVOT - (0.4, 0.0), motor_speed=1.0, motor_power=1.0, motor_on=True)
    builder.add_revolute_joint(right, hub, PIVOT + (0.4, 0.0), motor_speed=2.0, motor_power=1.0, motor_on=True)
    state = builder.build().replace(gravity=jnp.zeros(2))
    actions = np.zeros(STATIC.num_joints, np.float32)
    actions[:2] = 1.0
    _, traj = run_scene(state, STATIC, 20, motor=actions)
    mass, inertia = masses(state.bodies)
    bodies = [hub, left, right]
    spin = inertia[bodies] * traj.angular_velocity[:, bodies]
    orbit = mass[bodies] * np.cross(traj.position[:, bodies], traj.velocity[:, bodies])
    total = np.sum(spin + orbit, axis=1)
    scale = np.max(np.abs(spin), axis=1)
    measured("shared hub", wheel_speeds=traj.angular_velocity[-1, [left, right]].round(3).tolist(), total=total[-1])
    assert np.all(np.abs(traj.angular_velocity[-1, [left, right]]) > 0.5)  # the motors did work
    np.testing.assert_array_less(np.abs(total), 1e-4 * scale.max() + 1e-7)
