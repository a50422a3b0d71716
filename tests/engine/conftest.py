"""The engine tests' helpers: compiled rollouts (one compile per static size and length), batching, long runs of
one scene, analytic helpers and random scene generation.

Compiling a step takes tens of seconds on a 2-core CPU, so every multi-step test goes through
`run_batch`, which pads its scenes to `BATCH` and always runs `ROLLOUT_STEPS` steps with the same
`SimParams` structure: one compile of the vmapped scan serves all modules. Single scenes step through
`engine.step` itself (also compiled once per static size).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import sys
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from kforge import engine
from kforge.engine import SceneBuilder, SimParams, SimState, StaticSimParams, StepInfo
from kforge.engine.state import Bodies, ContactCache, Joints
from tests.helpers import scan_steps, stack

# Test modules import these helpers as `engine_test_helpers`, which works under every pytest import mode
# (`from conftest import ...` breaks under --import-mode=importlib and when several conftest.py files exist).
sys.modules["engine_test_helpers"] = sys.modules[__name__]

SIZE_S = StaticSimParams.for_size("s")
SIZE_M = StaticSimParams.for_size("m")
"""The static size of the batched rollouts (6 polygons incl. 4 reserved, 3 circles, 2 joints, 2 thrusters)."""
SIZE_L = StaticSimParams.for_size("l")

PARAMS = SimParams()
BATCH = 32
"""Every batched rollout is padded to this many scenes, so its compiled function is reused."""
ROLLOUT_STEPS = 200
"""Every batched rollout runs this many steps (tests look at the prefix they need)."""

ARENA = 5.0
FLOOR_TOP = 0.4


class Trajectory(NamedTuple):
    """Per-step results, leading axes ([batch,] steps): bodies, joints and contact cache after each step, and the
    step's info (with the initial state, everything needed to restart from any step)."""

    bodies: Bodies
    joints: Joints
    contacts: ContactCache
    info: StepInfo


# --------------------------------------------------------------------------- compiled rollouts
def _trajectory(state: SimState, info: StepInfo) -> Trajectory:
    return Trajectory(state.bodies, state.joints, state.contacts, info)


@functools.cache
def batched_rollout_fn(static: StaticSimParams):
    """jit(states, params, motor_actions (B, K, J), thruster_actions (B, K, T)) -> (final states, Trajectory), the
    scenes of the batch stepped side by side (params shared)."""
    return jax.jit(jax.vmap(scan_steps(static, _trajectory), in_axes=(0, None, 0, 0)))


def stack_states(states):
    return stack(*states)


def unstack(tree, index):
    return jax.tree_util.tree_map(lambda x: x[index], tree)


def to_numpy(tree):
    return jax.tree_util.tree_map(np.asarray, tree)


def zero_actions(static: StaticSimParams, num_steps: int = ROLLOUT_STEPS, batch: int | None = None):
    lead = (num_steps,) if batch is None else (batch, num_steps)
    return np.zeros(lead + (static.num_joints,), np.float32), np.zeros(lead + (static.num_thrusters,), np.float32)


def random_actions(
    rng: np.random.Generator, static: StaticSimParams, num_steps: int = ROLLOUT_STEPS, batch: int | None = None
):
    lead = (num_steps,) if batch is None else (batch, num_steps)
    motors = rng.uniform(-1.0, 1.0, lead + (static.num_joints,)).astype(np.float32)
    thrusters = rng.uniform(0.0, 1.0, lead + (static.num_thrusters,)).astype(np.float32)
    return motors, thrusters


def run_batch(
    states, motor_actions=None, thruster_actions=None, params: SimParams = PARAMS, static: StaticSimParams = SIZE_M
):
    """Run up to `BATCH` scenes for `ROLLOUT_STEPS` steps in one vmapped scan; numpy results, batch trimmed.

    Actions are (len(states), ROLLOUT_STEPS, J) and (len(states), ROLLOUT_STEPS, T); default zero.
    Returns (final states, Trajectory) with leading axes (len(states),) and (len(states), ROLLOUT_STEPS).
    """
    count = len(states)
    assert 1 <= count <= BATCH
    if motor_actions is None or thruster_actions is None:
        zero_m, zero_t = zero_actions(static, batch=count)
        motor_actions = zero_m if motor_actions is None else motor_actions
        thruster_actions = zero_t if thruster_actions is None else thruster_actions
    motor_actions = np.asarray(motor_actions, np.float32)
    thruster_actions = np.asarray(thruster_actions, np.float32)
    assert motor_actions.shape == (count, ROLLOUT_STEPS, static.num_joints)
    assert thruster_actions.shape == (count, ROLLOUT_STEPS, static.num_thrusters)
    pad = BATCH - count
    padded_states = list(states) + [states[0]] * pad
    motor_actions = np.concatenate([motor_actions, np.repeat(motor_actions[:1], pad, 0)])
    thruster_actions = np.concatenate([thruster_actions, np.repeat(thruster_actions[:1], pad, 0)])
    final, trajectory = batched_rollout_fn(static)(stack_states(padded_states), params, motor_actions, thruster_actions)
    trim = lambda tree: jax.tree_util.tree_map(lambda x: np.asarray(x)[:count], tree)  # noqa: E731
    return trim(final), trim(trajectory)


def python_loop(state, motor_actions, thruster_actions, params: SimParams = PARAMS, static: StaticSimParams = SIZE_M):
    """Step one scene with `engine.step` in a Python loop; returns the list of (state, info) after each step."""
    out = []
    for k in range(len(motor_actions)):
        state, info = engine.step(
            state, params, jnp.asarray(motor_actions[k]), jnp.asarray(thruster_actions[k]), static=static
        )
        out.append((state, info))
    return out


# --------------------------------------------------------------------------- analytic helpers
def rotate(angle, vector):
    """Rotate (..., 2) vectors by `angle` (shape broadcastable with the vectors' leading shape `...`), numpy."""
    angle = np.asarray(angle, np.float64)
    vector = np.asarray(vector, np.float64)
    c, s = np.cos(angle), np.sin(angle)
    return np.stack([c * vector[..., 0] - s * vector[..., 1], s * vector[..., 0] + c * vector[..., 1]], -1)


def cross(a, b):
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def masses(bodies):
    """(..., N) mass and inertia from inverse values (0 for static / inactive)."""
    inv_m, inv_i = np.asarray(bodies.inverse_mass, np.float64), np.asarray(bodies.inverse_inertia, np.float64)
    mass = np.where(inv_m > 0, 1.0 / np.where(inv_m > 0, inv_m, 1.0), 0.0)
    inertia = np.where(inv_i > 0, 1.0 / np.where(inv_i > 0, inv_i, 1.0), 0.0)
    return mass, inertia


def kinetic_energy(bodies, mass, inertia):
    v = np.asarray(bodies.velocity, np.float64)
    w = np.asarray(bodies.angular_velocity, np.float64)
    return 0.5 * np.sum(mass * np.sum(v * v, -1), -1) + 0.5 * np.sum(inertia * w * w, -1)


def bounding_radius(bodies):
    """(..., N) radius of the smallest origin-centred circle containing each shape."""
    poly = np.sqrt(np.max(np.sum(np.asarray(bodies.vertices, np.float64) ** 2, -1), -1))
    return np.where(np.asarray(bodies.n_vertices) > 0, poly, np.asarray(bodies.radius, np.float64))


# --------------------------------------------------------------------------- long runs of one scene
CHUNK = 100
"""Steps per compiled scan call."""

G = 9.81
"""[m/s^2] magnitude of the default gravity."""


@dataclasses.dataclass
class Motion:
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


def _motion_record(state: SimState, info: StepInfo) -> dict:
    return dict(
        position=state.bodies.position,
        rotation=state.bodies.rotation,
        velocity=state.bodies.velocity,
        angular_velocity=state.bodies.angular_velocity,
        normal_impulse=state.contacts.normal_impulse,
        motor_impulse=state.joints.motor_impulse,
        linear_impulse=state.joints.linear_impulse,
        angular_impulse=state.joints.angular_impulse,
        touching=info.touching,
        separation=info.separation,
    )


@functools.cache
def _chunk_runner(static: StaticSimParams):
    """jit(state, params, motor (CHUNK, J), thrust (CHUNK, T), valid_steps) -> (state, per-step record)."""
    return jax.jit(scan_steps(static, _motion_record, masked=True))


def _per_step(actions, steps: int, width: int) -> np.ndarray:
    """(steps, width) float32 actions from None (zeros), a constant (width,) vector or a (steps, width) array."""
    if actions is None:
        return np.zeros((steps, width), np.float32)
    actions = np.asarray(actions, np.float32)
    if actions.ndim == 1:
        return np.broadcast_to(actions, (steps, width)).copy()
    assert actions.shape == (steps, width), actions.shape
    return actions


def run(state, static: StaticSimParams, steps: int, params: SimParams | None = None, motor=None, thrust=None):
    """Run `steps` steps of one scene, CHUNK steps per compiled call; returns (final state, Motion).

    `motor` / `thrust`: None (zeros), one (J,) / (T,) action vector for every step, or (steps, J) / (steps, T).
    """
    params = SimParams() if params is None else params
    motor = _per_step(motor, steps, static.num_joints)
    thrust = _per_step(thrust, steps, static.num_thrusters)
    b = state.bodies
    initial = dict(position=b.position, rotation=b.rotation, velocity=b.velocity, angular_velocity=b.angular_velocity)
    records = [jax.tree_util.tree_map(lambda x: np.asarray(x)[None], initial)]  # the pose before the first step
    for start in range(0, steps, CHUNK):
        count = min(CHUNK, steps - start)
        m = np.zeros((CHUNK, static.num_joints), np.float32)
        t = np.zeros((CHUNK, static.num_thrusters), np.float32)
        m[:count], t[:count] = motor[start : start + count], thrust[start : start + count]
        state, record = _chunk_runner(static)(state, params, m, t, count)
        records.append(jax.tree_util.tree_map(lambda x, c=count: np.asarray(x)[:c], record))
    merged = {key: np.concatenate([r[key] for r in records if key in r]) for key in records[-1]}
    merged = {key: value.astype(np.float64) if value.dtype == np.float32 else value for key, value in merged.items()}
    return state, Motion(**merged)


def zero_gravity(state):
    return state.replace(gravity=jnp.zeros(2, jnp.float32))


def pair_index(static: StaticSimParams, body_a: int, body_b: int) -> int:
    """Index of the candidate pair {body_a, body_b} in `engine.pair_layout(static)`."""
    layout = engine.pair_layout(static)
    lo, hi = min(body_a, body_b), max(body_a, body_b)
    hits = np.flatnonzero((layout.body_a == lo) & (layout.body_b == hi))
    assert hits.size == 1, (body_a, body_b)
    return int(hits[0])


def world_vertices(traj: Motion, state, body: int) -> np.ndarray:
    """(n+1, V, 2) world vertices of polygon `body` along the trajectory."""
    count = int(state.bodies.n_vertices[body])
    local = np.asarray(state.bodies.vertices[body, :count], np.float64)
    return traj.position[:, body, None, :] + rotate(traj.rotation[:, body, None], local[None])


def joint_anchor_error(traj: Motion, state, joint: int) -> np.ndarray:
    """(n+1,) [m] distance between the two world anchors of `joint` along the trajectory."""
    j = state.joints
    a, b = int(j.body_a[joint]), int(j.body_b[joint])
    pa = traj.position[:, a] + rotate(traj.rotation[:, a], np.asarray(j.anchor_a[joint], np.float64))
    pb = traj.position[:, b] + rotate(traj.rotation[:, b], np.asarray(j.anchor_b[joint], np.float64))
    return np.linalg.norm(pb - pa, axis=-1)


def speed(traj: Motion, body: int) -> np.ndarray:
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


# --------------------------------------------------------------------------- random scenes
def _random_polygon(rng):
    """Local vertices of a random box or triangle of size ~0.15-0.6 m (counter-clockwise or clockwise)."""
    if rng.random() < 0.6:
        w, h = rng.uniform(0.15, 0.6, 2)
        verts = np.array([[-w / 2, -h / 2], [w / 2, -h / 2], [w / 2, h / 2], [-w / 2, h / 2]])
    else:
        while True:
            verts = rng.uniform(-0.3, 0.3, (3, 2))
            area = 0.5 * abs(cross(verts[1] - verts[0], verts[2] - verts[0]))
            edges = np.linalg.norm(np.roll(verts, -1, 0) - verts, axis=1)
            if area > 0.02 and edges.min() > 0.12:
                break
    if rng.random() < 0.5:
        verts = verts[::-1].copy()
    return verts


def random_scene(
    rng: np.random.Generator,
    static: StaticSimParams = SIZE_M,
    *,
    overlapping: bool,
    joints: bool = True,
    thrusters: bool = True,
    statics: bool = True,
) -> SimState:
    """A random Kinetix-style scene: boundaries, random boxes/triangles/circles, joints and thrusters.

    With `overlapping=False`, shapes start apart from each other and from the boundaries (by bounding circles).
    """
    builder = SceneBuilder(static)
    placed: list[tuple[np.ndarray, float]] = []

    def place(radius):
        for _ in range(200):
            if overlapping:  # anywhere in the arena, possibly into the boundaries
                pos = np.array([rng.uniform(0.05, ARENA - 0.05), rng.uniform(FLOOR_TOP - 0.1, ARENA - 0.05)])
            else:
                lo, hi = radius + 0.02, ARENA - radius - 0.02
                pos = np.array([rng.uniform(lo, hi), rng.uniform(FLOOR_TOP + radius + 0.02, ARENA - radius - 0.02)])
            if overlapping or all(np.linalg.norm(pos - p) > radius + r + 0.02 for p, r in placed):
                placed.append((pos, radius))
                return pos
        return None

    def material():
        is_static = statics and rng.random() < 0.15
        return dict(
            density=float(rng.uniform(0.5, 3.0)),
            friction=float(rng.uniform(0.0, 1.0)),
            restitution=float(rng.choice([0.0, rng.uniform(0.0, 1.0)])),
            collision_mode=int(rng.choice([0, 1, 1, 2])),
            static=is_static,
            velocity=(0.0, 0.0) if is_static else tuple(rng.uniform(-2.0, 2.0, 2)),
            angular_velocity=0.0 if is_static else float(rng.uniform(-3.0, 3.0)),
        )

    movable: list[int] = []
    for _ in range(static.num_polygons - static.num_reserved_static):
        if rng.random() < 0.85:
            verts = _random_polygon(rng)
            pos = place(float(np.max(np.linalg.norm(verts, axis=1))))
            if pos is None:
                continue
            kw = material()
            index = builder.add_polygon(pos, verts, rotation=float(rng.uniform(-np.pi, np.pi)), **kw)
            if not kw["static"]:
                movable.append(index)
    for _ in range(static.num_circles):
        if rng.random() < 0.85:
            radius = float(rng.uniform(0.08, 0.35))
            pos = place(radius)
            if pos is None:
                continue
            kw = material()
            index = builder.add_circle(pos, radius, **kw)
            if not kw["static"]:
                movable.append(index)
    state = builder.build()
    active = np.flatnonzero(np.asarray(state.bodies.active))
    positions = np.asarray(state.bodies.position, np.float64)
    if joints and movable:
        for _ in range(static.num_joints):
            if rng.random() < 0.7:
                a = int(rng.choice(movable))
                others = [int(i) for i in active if i != a]
                b = int(rng.choice(others))
                anchor = (
                    0.5 * (positions[a] + positions[b])
                    if rng.random() < 0.5
                    else positions[a] + rng.uniform(-0.1, 0.1, 2)
                )
                if rng.random() < 0.3:
                    builder.add_fixed_joint(a, b, anchor)
                else:
                    limits = None if rng.random() < 0.5 else (-float(rng.uniform(0, 1.5)), float(rng.uniform(0, 1.5)))
                    builder.add_revolute_joint(
                        a,
                        b,
                        anchor,
                        motor_speed=float(rng.uniform(-2, 2)),
                        motor_power=float(rng.uniform(0, 3)),
                        motor_on=bool(rng.random() < 0.6),
                        limits=limits,
                    )
    if thrusters and movable:
        for _ in range(static.num_thrusters):
            if rng.random() < 0.8:
                body = int(rng.choice(movable))
                builder.add_thruster(
                    body,
                    positions[body] + rng.uniform(-0.1, 0.1, 2),
                    float(rng.uniform(-np.pi, np.pi)),
                    float(rng.uniform(0.0, 3.0)),
                )
    return builder.build()


@pytest.fixture(scope="session")
def static_m() -> StaticSimParams:
    return SIZE_M


@pytest.fixture(scope="session")
def params() -> SimParams:
    return PARAMS
