"""Demo: simulate a small size-m scene (a motorised vehicle with a thruster and a stacked box, a ball) to a GIF
(`kforge demo [--out outputs/engine_demo.gif] [--steps 240]`)."""

from __future__ import annotations

import functools
import time
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from kforge.engine.params import SimParams, StaticSimParams
from kforge.engine.physics_step import step
from kforge.engine.render import render_frame, write_gif
from kforge.engine.scene import FLOOR_TOP, SceneBuilder
from kforge.engine.state import SimState

RENDER_EVERY = 2
"""Render every this many steps; the GIF plays in real time at 1 / (RENDER_EVERY * dt) frames per second."""

SIZE = "m"

# Vehicle: a box chassis, level with the axle of its motorised front wheel; its tail slides on the floor.
WHEEL_RADIUS_M = 0.15
WHEEL_CENTRE_M = (1.35, FLOOR_TOP + WHEEL_RADIUS_M)
CHASSIS_SIZE_M = (1.0, 0.24)
CHASSIS_CENTRE_M = (1.0, WHEEL_CENTRE_M[1])
CHASSIS_FRICTION = 0.1  # [-] low, so the dragging tail slides
MOTOR_SPEED = -0.5  # [-] units of SimParams.base_motor_speed; negative = clockwise wheel = drives towards +x
MOTOR_POWER = 1.0  # [-] units of SimParams.base_motor_power
THRUSTER_ANCHOR_M = (CHASSIS_CENTRE_M[0] - CHASSIS_SIZE_M[0] / 2, CHASSIS_CENTRE_M[1])  # rear end of the chassis
THRUSTER_ANGLE_RAD = 0.0  # pushes towards +x
THRUSTER_POWER = 0.05  # [-] units of SimParams.base_thruster_power (0.5 N at full action)

# Cargo: a box stacked on the chassis.
CARGO_SIZE_M = (0.3, 0.3)
CARGO_CENTRE_M = (0.85, CHASSIS_CENTRE_M[1] + (CHASSIS_SIZE_M[1] + CARGO_SIZE_M[1]) / 2)

# Ball: dropped on the right, rolling left towards the vehicle.
BALL_RADIUS_M = 0.25
BALL_CENTRE_M = (4.2, 1.2)
BALL_VELOCITY_M_S = (-1.5, 0.0)
BALL_RESTITUTION = 0.3


class DemoScene(NamedTuple):
    """The initial state, its static params, and the chassis body index (for the summary)."""

    state: SimState
    static: StaticSimParams
    chassis: int


def build_scene() -> DemoScene:
    """The demo scene in Kinetix size m, whose 2 free polygon slots hold the chassis and the cargo box."""
    static = StaticSimParams.for_size(SIZE)
    builder = SceneBuilder(static)
    chassis = builder.add_box(CHASSIS_CENTRE_M, CHASSIS_SIZE_M, friction=CHASSIS_FRICTION)
    builder.add_box(CARGO_CENTRE_M, CARGO_SIZE_M)
    wheel = builder.add_circle(WHEEL_CENTRE_M, WHEEL_RADIUS_M)
    builder.add_revolute_joint(
        chassis, wheel, WHEEL_CENTRE_M, motor_on=True, motor_speed=MOTOR_SPEED, motor_power=MOTOR_POWER
    )
    builder.add_thruster(chassis, THRUSTER_ANCHOR_M, THRUSTER_ANGLE_RAD, power=THRUSTER_POWER)
    builder.add_circle(BALL_CENTRE_M, BALL_RADIUS_M, velocity=BALL_VELOCITY_M_S, restitution=BALL_RESTITUTION)
    return DemoScene(builder.build(), static, chassis)


@functools.partial(jax.jit, static_argnames="static")
def rollout(
    state: SimState,
    params: SimParams,
    motor_actions: jnp.ndarray,
    thruster_actions: jnp.ndarray,
    static: StaticSimParams,
) -> SimState:
    """States after each of S steps, stacked on a leading axis; actions are (S, J) and (S, T)."""

    def one_step(current, actions):
        following, _ = step(current, params, *actions, static=static)
        return following, following

    _, states = jax.lax.scan(one_step, state, (motor_actions, thruster_actions))
    return states


def write_demo(out: str, steps: int) -> tuple[str, str]:
    """Simulate the demo scene for `steps` physics steps (at least `RENDER_EVERY`), render every `RENDER_EVERY`-th
    step and write the GIF to `out`; returns its path and a one-line summary."""
    if steps < RENDER_EVERY:
        raise ValueError(f"the demo needs at least {RENDER_EVERY} steps, got {steps}")
    started = time.perf_counter()
    scene = build_scene()
    params = SimParams()
    motor_actions = jnp.ones((steps, scene.static.num_joints))
    thruster_actions = jnp.ones((steps, scene.static.num_thrusters))
    states = jax.device_get(rollout(scene.state, params, motor_actions, thruster_actions, static=scene.static))
    wall = time.perf_counter() - started

    rendered_steps = range(RENDER_EVERY - 1, steps, RENDER_EVERY)
    frames = [render_frame(jax.tree.map(lambda x, t=t: x[t], states)) for t in rendered_steps]
    path = write_gif(frames, out, fps=1.0 / (RENDER_EVERY * params.dt))
    positions = states.bodies.position
    travel = positions[-1, scene.chassis, 0] - scene.state.bodies.position[scene.chassis, 0]
    finite = bool(np.all(np.isfinite(positions)))
    summary = (
        f"{steps} steps ({steps * params.dt:.1f} s simulated, {wall:.1f} s wall incl. compile), "
        f"{len(frames)} frames; vehicle moved {travel:+.2f} m in x; positions finite: {finite}"
    )
    return str(path), summary
