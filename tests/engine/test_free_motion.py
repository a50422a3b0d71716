"""Test group B: free motion matches the closed form of the integrator (float32 exactness, rtol 1e-5).

The step runs `num_substeps` semi-implicit Euler substeps of h = dt / num_substeps, so after k substeps from
(y0, v0) under constant acceleration a: v = v0 + k h a and y = y0 + k h v0 + h^2 a k (k + 1) / 2.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest
from engine_test_helpers import PARAMS, SIZE_M, cross, rotate

from kforge import engine
from kforge.engine import SceneBuilder
from tests.rollouts import run_batch

pytestmark = pytest.mark.smoke

RTOL = 1e-5
CHECK_STEPS = 30
H = PARAMS.dt / SIZE_M.num_substeps
G = -9.81


def _closed_form(x0, v0, a, substeps):
    k = np.asarray(substeps, np.float64)
    return x0 + k * H * v0 + H**2 * a * k * (k + 1) / 2, v0 + k * H * a


def _assert_close(got, expected, scale):
    np.testing.assert_allclose(got, expected, rtol=RTOL, atol=RTOL * scale)


@pytest.fixture(scope="module")
def scenes():
    """Gravity scene and zero-gravity scene (no boundaries, bodies far apart), with junk in inactive slots."""
    b = SceneBuilder(SIZE_M, boundaries=False)
    fall = b.add_box((1.0, 4.0), (0.3, 0.2), rotation=0.3, velocity=(0.0, 1.0))
    projectile = b.add_circle((4.0, 2.0), 0.1, velocity=(-2.5, 3.0), angular_velocity=1.5)
    spinner = b.add_box((-3.0, 3.0), (0.5, 0.1), angular_velocity=2.0)
    gravity_state = b.build()

    b = SceneBuilder(SIZE_M, boundaries=False)
    spin = b.add_box((1.0, 1.0), (0.6, 0.2), rotation=0.2, angular_velocity=3.7)
    glide = b.add_circle((-4.0, -2.0), 0.2, velocity=(0.8, -0.3), angular_velocity=-5.0)
    zero_g = b.build().replace(gravity=jnp.zeros(2))
    zero_g = _with_inactive_junk(zero_g)
    gravity_state = _with_inactive_junk(gravity_state)
    final, traj = run_batch([gravity_state, zero_g])
    return dict(
        states=(gravity_state, zero_g),
        traj=traj,
        final=final,
        fall=fall,
        projectile=projectile,
        spinner=spinner,
        spin=spin,
        glide=glide,
    )


def _with_inactive_junk(state):
    """Inactive slots with non-zero pose, velocity and mass (Jax2D integrated such slots: W7)."""
    b = state.bodies
    inactive = ~np.asarray(b.active)
    assert inactive.any()
    n = inactive.size
    rng = np.random.default_rng(1)
    junk = lambda x, values: jnp.where(  # noqa: E731
        jnp.asarray(inactive).reshape((-1,) + (1,) * (x.ndim - 1)), jnp.asarray(values, x.dtype), x
    )
    return state.replace(
        bodies=b.replace(
            position=junk(b.position, rng.uniform(0.5, 4.5, (n, 2))),
            rotation=junk(b.rotation, rng.uniform(-3, 3, n)),
            velocity=junk(b.velocity, rng.uniform(-3, 3, (n, 2))),
            angular_velocity=junk(b.angular_velocity, rng.uniform(-3, 3, n)),
            inverse_mass=junk(b.inverse_mass, np.ones(n)),
            inverse_inertia=junk(b.inverse_inertia, np.ones(n)),
        )
    )


def test_free_fall_matches_discrete_closed_form(scenes):
    traj = scenes["traj"].bodies
    i = scenes["fall"]
    steps = np.arange(1, CHECK_STEPS + 1)
    y, vy = _closed_form(4.0, 1.0, G, SIZE_M.num_substeps * steps)
    got_y = traj.position[0, :CHECK_STEPS, i, 1]
    got_vy = traj.velocity[0, :CHECK_STEPS, i, 1]
    _assert_close(got_y, y, scale=4.0)
    _assert_close(got_vy, vy, scale=1.0 + abs(G) * CHECK_STEPS * PARAMS.dt)
    # No horizontal motion, no rotation.
    np.testing.assert_array_equal(traj.position[0, :CHECK_STEPS, i, 0], np.float32(1.0))
    np.testing.assert_array_equal(traj.velocity[0, :CHECK_STEPS, i, 0], 0.0)
    np.testing.assert_array_equal(traj.angular_velocity[0, :CHECK_STEPS, i], 0.0)
    np.testing.assert_array_equal(traj.rotation[0, :CHECK_STEPS, i], np.float32(0.3))


def test_free_fall_does_not_depend_on_the_other_bodies(scenes):
    """The spinning box falls with the same closed form as the non-spinning one."""
    traj = scenes["traj"].bodies
    i = scenes["spinner"]
    steps = np.arange(1, CHECK_STEPS + 1)
    y, vy = _closed_form(3.0, 0.0, G, SIZE_M.num_substeps * steps)
    _assert_close(traj.position[0, :CHECK_STEPS, i, 1], y, scale=3.0)
    _assert_close(traj.velocity[0, :CHECK_STEPS, i, 1], vy, scale=abs(G) * CHECK_STEPS * PARAMS.dt)
    theta, _ = _closed_form(0.0, 2.0, 0.0, SIZE_M.num_substeps * steps)
    _assert_close(traj.rotation[0, :CHECK_STEPS, i], theta, scale=2.0)


def test_projectile(scenes):
    traj = scenes["traj"].bodies
    i = scenes["projectile"]
    steps = np.arange(1, CHECK_STEPS + 1)
    substeps = SIZE_M.num_substeps * steps
    x, vx = _closed_form(4.0, -2.5, 0.0, substeps)
    y, vy = _closed_form(2.0, 3.0, G, substeps)
    _assert_close(traj.position[0, :CHECK_STEPS, i, 0], x, scale=4.0)
    np.testing.assert_array_equal(traj.velocity[0, :CHECK_STEPS, i, 0], np.float32(-2.5))
    _assert_close(traj.position[0, :CHECK_STEPS, i, 1], y, scale=2.0)
    _assert_close(traj.velocity[0, :CHECK_STEPS, i, 1], vy, scale=3.0)
    # x is linear in time: constant differences between steps.
    dx = np.diff(np.asarray(traj.position[0, :CHECK_STEPS, i, 0], np.float64))
    np.testing.assert_allclose(dx, -2.5 * PARAMS.dt, rtol=1e-4)
    np.testing.assert_array_equal(traj.angular_velocity[0, :CHECK_STEPS, i], np.float32(1.5))


def test_spin_in_zero_gravity_keeps_angular_velocity(scenes):
    traj = scenes["traj"].bodies
    for i, theta0, omega, position in [(scenes["spin"], 0.2, 3.7, (1.0, 1.0))]:
        np.testing.assert_allclose(traj.angular_velocity[1, :, i], omega, rtol=1e-6)
        np.testing.assert_array_equal(traj.velocity[1, :, i], 0.0)
        np.testing.assert_allclose(
            traj.position[1, :, i], np.broadcast_to(position, traj.position[1, :, i].shape), rtol=1e-6
        )
        theta, _ = _closed_form(theta0, omega, 0.0, SIZE_M.num_substeps * np.arange(1, CHECK_STEPS + 1))
        _assert_close(traj.rotation[1, :CHECK_STEPS, i], theta, scale=abs(theta0) + abs(omega))


def test_constant_velocity_in_zero_gravity(scenes):
    traj = scenes["traj"].bodies
    i = scenes["glide"]
    np.testing.assert_allclose(
        traj.velocity[1, :, i], np.broadcast_to([0.8, -0.3], traj.velocity[1, :, i].shape), rtol=1e-6
    )
    np.testing.assert_allclose(traj.angular_velocity[1, :, i], -5.0, rtol=1e-6)
    steps = np.arange(1, CHECK_STEPS + 1)
    x, _ = _closed_form(-4.0, 0.8, 0.0, SIZE_M.num_substeps * steps)
    y, _ = _closed_form(-2.0, -0.3, 0.0, SIZE_M.num_substeps * steps)
    _assert_close(traj.position[1, :CHECK_STEPS, i, 0], x, scale=4.0)
    _assert_close(traj.position[1, :CHECK_STEPS, i, 1], y, scale=2.0)


def test_inactive_slots_do_not_move(scenes):
    """W7 regression: inactive slots keep their (junk) pose and velocity bitwise, every step, even with mass."""
    traj = scenes["traj"].bodies
    for scene, state in enumerate(scenes["states"]):
        inactive = ~np.asarray(state.bodies.active)
        for field in ("position", "rotation", "velocity", "angular_velocity"):
            initial = np.asarray(getattr(state.bodies, field))[inactive]
            got = np.asarray(getattr(traj, field))[scene][:, inactive]
            np.testing.assert_array_equal(got, np.broadcast_to(initial, got.shape), err_msg=f"scene {scene} {field}")


# --------------------------------------------------------------------------- thrusters, one step
@pytest.fixture(scope="module")
def thruster_scene():
    b = SceneBuilder(SIZE_M, boundaries=False)
    box_rotation = 0.4
    box = b.add_box((1.0, 2.0), (0.4, 0.2), rotation=box_rotation, density=2.0)
    circle = b.add_circle((3.0, 3.0), 0.25, density=0.7)
    lever = rotate(box_rotation, np.array([0.15, 0.05]))  # world lever from the box's centre
    b.add_thruster(box, np.array([1.0, 2.0]) + lever, 1.1, 1.5)
    b.add_thruster(circle, (3.0, 3.0), 2.5, 0.8)  # through the centre of mass
    state = b.build().replace(gravity=jnp.zeros(2))
    return state, box, circle, lever


def _one_step(state, thruster_actions):
    return engine.step(
        state, PARAMS, jnp.zeros(SIZE_M.num_joints), jnp.asarray(thruster_actions, jnp.float32), static=SIZE_M
    )


def test_thruster_one_step_offset(thruster_scene):
    state, box, _, lever = thruster_scene
    action = 0.7
    new, _ = _one_step(state, [action, 0.0])
    mass = 2.0 * 0.4 * 0.2
    inertia = mass * (0.4**2 + 0.2**2) / 12
    force = PARAMS.base_thruster_power * 1.5 * action * np.array([np.cos(1.1), np.sin(1.1)])
    torque = float(cross(lever, force))
    dt = PARAMS.dt
    n = SIZE_M.num_substeps
    np.testing.assert_allclose(np.asarray(new.bodies.velocity[box]), force * dt / mass, rtol=RTOL)
    np.testing.assert_allclose(float(new.bodies.angular_velocity[box]), torque * dt / inertia, rtol=RTOL)
    # Positions follow the same semi-implicit closed form with the force held over the step.
    dx = H**2 * (force / mass) * n * (n + 1) / 2
    np.testing.assert_allclose(np.asarray(new.bodies.position[box]) - np.array([1.0, 2.0]), dx, rtol=1e-4)
    dtheta = H**2 * (torque / inertia) * n * (n + 1) / 2
    np.testing.assert_allclose(float(new.bodies.rotation[box]) - 0.4, dtheta, rtol=1e-4)


def test_thruster_through_centre_of_mass_gives_no_torque(thruster_scene):
    state, _, circle, _ = thruster_scene
    action = 0.9
    new, _ = _one_step(state, [0.0, action])
    mass = 0.7 * np.pi * 0.25**2
    force = PARAMS.base_thruster_power * 0.8 * action * np.array([np.cos(2.5), np.sin(2.5)])
    np.testing.assert_allclose(np.asarray(new.bodies.velocity[circle]), force * PARAMS.dt / mass, rtol=RTOL)
    assert float(new.bodies.angular_velocity[circle]) == 0.0
    assert float(new.bodies.rotation[circle]) == 0.0


def test_thruster_off_does_nothing(thruster_scene):
    state, box, circle, _ = thruster_scene
    new, _ = _one_step(state, [0.0, 0.0])
    for i in (box, circle):
        np.testing.assert_array_equal(np.asarray(new.bodies.velocity[i]), 0.0)
        assert float(new.bodies.angular_velocity[i]) == 0.0


def test_thruster_direction_follows_body_rotation(thruster_scene):
    """Rotating the body rotates the thrust: the thruster angle is fixed in the body frame."""
    state, box, _, _ = thruster_scene
    turned = state.replace(bodies=state.bodies.replace(rotation=state.bodies.rotation.at[box].add(0.5)))
    new, _ = _one_step(turned, [1.0, 0.0])
    mass = 2.0 * 0.4 * 0.2
    force = PARAMS.base_thruster_power * 1.5 * np.array([np.cos(1.6), np.sin(1.6)])
    np.testing.assert_allclose(np.asarray(new.bodies.velocity[box]), force * PARAMS.dt / mass, rtol=RTOL)
