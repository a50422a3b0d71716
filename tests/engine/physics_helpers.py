"""Shared helpers of the physics-behaviour tests (contacts, joints): compiled multi-step runners and geometry.

`simulate` runs a scene for any number of steps with one compiled `jax.lax.scan` per `StaticSimParams`:
steps are run in chunks of `CHUNK` steps, and steps past the requested count leave the state unchanged,
so the step count does not trigger recompilation and the final state is exactly the requested one.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

import engine
from engine import SimParams, StaticSimParams

CHUNK = 100
"""Steps per compiled scan call."""

G = 9.81
"""[m/s^2] magnitude of the default gravity."""

# Static sizes shared by all physics tests (one compiled runner each).
SIZE_S = StaticSimParams.for_size("s")
SIZE_M = StaticSimParams.for_size("m")
SIZE_L = StaticSimParams.for_size("l")


@dataclasses.dataclass
class Trajectory:
    """Per-step record of a run of n steps (numpy, float64 where float).

    Pose arrays have n + 1 rows: row k is the state after k steps (row 0 = initial state).
    Per-step arrays have n rows: row k describes step k + 1 (impulses at its end, `touching` and
    `separation` from StepInfo, i.e. measured at the start of that step).
    """

    position: np.ndarray  # (n+1, N, 2)
    rotation: np.ndarray  # (n+1, N)
    velocity: np.ndarray  # (n+1, N, 2)
    angular_velocity: np.ndarray  # (n+1, N)
    normal_impulse: np.ndarray  # (n, K, 2) contact impulses (per substep) of the last substep of each step
    motor_impulse: np.ndarray  # (n, J)
    linear_impulse: np.ndarray  # (n, J, 2)
    angular_impulse: np.ndarray  # (n, J)
    touching: np.ndarray  # (n, K) bool
    separation: np.ndarray  # (n, K)

    @property
    def num_steps(self) -> int:
        return self.rotation.shape[0] - 1


@functools.cache
def _chunk_runner(static: StaticSimParams):
    """jit(state, params, motor (CHUNK, J), thrust (CHUNK, T), valid_steps) -> (state, per-step record)."""

    def run(state, params, motor, thrust, valid_steps):
        def body(carry, inputs):
            index, motor_action, thrust_action = inputs
            new, info = engine.step(carry, params, motor_action, thrust_action, static=static)
            keep = index < valid_steps
            new = jax.tree_util.tree_map(lambda n, o: jnp.where(keep, n, o), new, carry)
            record = dict(
                position=new.bodies.position,
                rotation=new.bodies.rotation,
                velocity=new.bodies.velocity,
                angular_velocity=new.bodies.angular_velocity,
                normal_impulse=new.contacts.normal_impulse,
                motor_impulse=new.joints.motor_impulse,
                linear_impulse=new.joints.linear_impulse,
                angular_impulse=new.joints.angular_impulse,
                touching=info.touching,
                separation=info.separation,
            )
            return new, record

        return jax.lax.scan(body, state, (jnp.arange(CHUNK), motor, thrust))

    return jax.jit(run)


def _per_step(actions, steps: int, width: int) -> np.ndarray:
    """(steps, width) float32 actions from None (zeros), a constant (width,) vector or a (steps, width) array."""
    if actions is None:
        return np.zeros((steps, width), np.float32)
    actions = np.asarray(actions, np.float32)
    if actions.ndim == 1:
        return np.broadcast_to(actions, (steps, width)).copy()
    assert actions.shape == (steps, width), actions.shape
    return actions


def simulate(state, static: StaticSimParams, steps: int, params: SimParams | None = None, motor=None, thrust=None):
    """Run `steps` steps; returns (final state, dict of per-step records).

    `motor` / `thrust`: None (zeros), one (J,) / (T,) action vector for every step, or (steps, J) / (steps, T).
    """
    params = SimParams() if params is None else params
    motor = _per_step(motor, steps, static.num_joints)
    thrust = _per_step(thrust, steps, static.num_thrusters)
    runner = _chunk_runner(static)
    records = []
    for start in range(0, steps, CHUNK):
        count = min(CHUNK, steps - start)
        m = np.zeros((CHUNK, static.num_joints), np.float32)
        t = np.zeros((CHUNK, static.num_thrusters), np.float32)
        m[:count], t[:count] = motor[start : start + count], thrust[start : start + count]
        state, record = runner(state, params, m, t, count)
        records.append(jax.tree_util.tree_map(lambda x, c=count: np.asarray(x)[:c], record))
    merged = {key: np.concatenate([r[key] for r in records]) for key in records[0]}
    merged = {key: value.astype(np.float64) if value.dtype == np.float32 else value for key, value in merged.items()}
    return state, merged


def run(state, static: StaticSimParams, steps: int, params: SimParams | None = None, motor=None, thrust=None):
    """Like `simulate`, returning (final state, Trajectory) with the initial pose prepended."""
    b = state.bodies
    initial = dict(
        position=np.asarray(b.position, np.float64)[None],
        rotation=np.asarray(b.rotation, np.float64)[None],
        velocity=np.asarray(b.velocity, np.float64)[None],
        angular_velocity=np.asarray(b.angular_velocity, np.float64)[None],
    )
    final, merged = simulate(state, static, steps, params, motor, thrust)
    for key, first in initial.items():
        merged[key] = np.concatenate([first, merged[key]])
    return final, Trajectory(**merged)


# --------------------------------------------------------------------------- scene helpers
def zero_gravity(state):
    return state.replace(gravity=jnp.zeros(2, jnp.float32))


def pair_index(static: StaticSimParams, body_a: int, body_b: int) -> int:
    """Index of the candidate pair {body_a, body_b} in `engine.pair_layout(static)`."""
    layout = engine.pair_layout(static)
    lo, hi = min(body_a, body_b), max(body_a, body_b)
    hits = np.flatnonzero((layout.body_a == lo) & (layout.body_b == hi))
    assert hits.size == 1, (body_a, body_b)
    return int(hits[0])


def rotate_np(angle, vector):
    """Rotate (..., 2) vectors by `angle` (shape broadcastable with the vectors' leading shape `...`), numpy."""
    angle = np.asarray(angle, np.float64)
    vector = np.asarray(vector, np.float64)
    c, s = np.cos(angle), np.sin(angle)
    return np.stack([c * vector[..., 0] - s * vector[..., 1], s * vector[..., 0] + c * vector[..., 1]], -1)


def world_vertices(traj: Trajectory, state, body: int) -> np.ndarray:
    """(n+1, V, 2) world vertices of polygon `body` along the trajectory."""
    count = int(state.bodies.n_vertices[body])
    local = np.asarray(state.bodies.vertices[body, :count], np.float64)
    return traj.position[:, body, None, :] + rotate_np(traj.rotation[:, body, None], local[None])


def joint_anchor_error(traj: Trajectory, state, joint: int) -> np.ndarray:
    """(n+1,) [m] distance between the two world anchors of `joint` along the trajectory."""
    j = state.joints
    a, b = int(j.body_a[joint]), int(j.body_b[joint])
    pa = traj.position[:, a] + rotate_np(traj.rotation[:, a], np.asarray(j.anchor_a[joint], np.float64))
    pb = traj.position[:, b] + rotate_np(traj.rotation[:, b], np.asarray(j.anchor_b[joint], np.float64))
    return np.linalg.norm(pb - pa, axis=-1)


def speed(traj: Trajectory, body: int) -> np.ndarray:
    """(n+1,) [m/s] linear speed of `body`."""
    return np.linalg.norm(traj.velocity[:, body], axis=-1)


def crossings(signal: np.ndarray, dt: float, direction: int = 1) -> np.ndarray:
    """Times [s] (linear interpolation) at which `signal` (sampled every dt from t = 0) crosses zero upward
    (direction = 1) or downward (-1)."""
    s = direction * np.asarray(signal, np.float64)
    k = np.flatnonzero((s[:-1] < 0) & (s[1:] >= 0))
    return (k + s[k] / (s[k] - s[k + 1])) * dt


def elliptic_k(k: float) -> float:
    """Complete elliptic integral of the first kind K(k) (modulus k) by the arithmetic-geometric mean."""
    a, b = 1.0, math.sqrt(1.0 - k * k)
    for _ in range(40):
        a, b = 0.5 * (a + b), math.sqrt(a * b)
    return math.pi / (2.0 * a)
