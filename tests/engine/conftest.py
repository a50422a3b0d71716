"""The engine tests' helpers: static sizes, analytic helpers and random scene generation. The rollouts (batched,
long runs of one scene, Python loops) are the shared ones of tests/rollouts.py.

Compiling a step takes tens of seconds on a 2-core CPU, so every multi-step test of many scenes goes through
`tests.rollouts.run_batch`, which pads its scenes to `BATCH` and always runs `ROLLOUT_STEPS` steps with the same
`SimParams` structure: one compile of the vmapped scan serves all modules. Single scenes step through
`engine.step` itself (also compiled once per static size) or `run_scene`.
"""

from __future__ import annotations

import math
import sys

import jax.numpy as jnp
import numpy as np
import pytest

from kforge import engine
from kforge.engine import SceneBuilder, SimParams, SimState, StaticSimParams
from tests.rollouts import BATCH_STATIC, PARAMS, Motion

# Test modules import these helpers as `engine_test_helpers`, which works under every pytest import mode
# (`from conftest import ...` breaks under --import-mode=importlib and when several conftest.py files exist).
sys.modules["engine_test_helpers"] = sys.modules[__name__]

SIZE_S = StaticSimParams.for_size("s")
SIZE_M = BATCH_STATIC
"""Size m, that of the batched rollouts (6 polygons incl. 4 reserved, 3 circles, 2 joints, 2 thrusters)."""
SIZE_L = StaticSimParams.for_size("l")

ARENA = 5.0
FLOOR_TOP = 0.4


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


G = 9.81
"""[m/s^2] magnitude of the default gravity."""


# --------------------------------------------------------------------------- scenes and their runs (`run_scene`)
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
