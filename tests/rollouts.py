"""The rollouts every test folder shares, each compiled once per static size (and length) and reused across modules.

Engine, built on `scan_steps` (a `lax.scan` of `engine.step`):
- `run_batch`: up to `BATCH` scenes stepped side by side for `ROLLOUT_STEPS` steps (vmapped scan) -> `Trajectory`;
- `run_scene`: one scene for any number of steps, `CHUNK` steps per compiled call -> `Motion`;
- `python_loop`: one scene through `engine.step` in a Python loop, the reference for vmap and jit.

Env:
- `env_episodes`: a batch of levels played from their starts with given actions (vmapped scan of `env.step`);
- `env_loop`: one level played with the jitted `env.step`, one call per action, the program a replay of stored states
  also runs (so a replay reproduces its states bit for bit).

Test modules import them as `from tests.rollouts import ...`.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from kforge import engine, env
from kforge.engine import SimParams, SimState, StaticSimParams, StepInfo
from kforge.engine.state import Bodies, ContactCache, Joints
from tests.helpers import stack

BATCH = 32
"""Every batched rollout is padded to this many scenes, so its compiled function is reused."""
ROLLOUT_STEPS = 200
"""Every batched rollout runs this many steps (tests look at the prefix they need)."""
BATCH_STATIC = StaticSimParams.for_size("m")
"""The default static size of the batched rollouts (6 polygons incl. 4 reserved, 3 circles, 2 joints, 2 thrusters)."""
PARAMS = SimParams()
"""The default physics parameters of the engine rollouts."""
CHUNK = 100
"""Steps per compiled call of `run_scene`."""


def scan_steps(static: StaticSimParams, record: Callable[[SimState, StepInfo], object], masked: bool = False):
    """`scan(state, params, motor_actions (K, J), thruster_actions (K, T)[, valid_steps])` -> (final state, per-step
    `record(state after the step, its StepInfo)` stacked over K), a `lax.scan` of `engine.step` to jit or vmap.

    `masked`: steps from `valid_steps` on leave the state as it was, so that one compiled length serves every
    shorter run.
    """

    def scan(state, params, motor_actions, thruster_actions, valid_steps=None):
        def body(carry, inputs):
            index, motor, thrust = inputs
            new, info = engine.step(carry, params, motor, thrust, static=static)
            if masked:
                new = jax.tree.map(lambda after, before: jnp.where(index < valid_steps, after, before), new, carry)
            return new, record(new, info)

        return jax.lax.scan(body, state, (jnp.arange(motor_actions.shape[0]), motor_actions, thruster_actions))

    return scan


# --------------------------------------------------------------------------- batches of scenes
class Trajectory(NamedTuple):
    """Per-step results of `run_batch`, leading axes (batch, steps): bodies, joints and contact cache after each
    step, and the step's info (with the initial state, everything needed to restart from any step)."""

    bodies: Bodies
    joints: Joints
    contacts: ContactCache
    info: StepInfo


def _trajectory(state: SimState, info: StepInfo) -> Trajectory:
    return Trajectory(state.bodies, state.joints, state.contacts, info)


@functools.cache
def _batched_scan(static: StaticSimParams):
    """jit(states, params, motor_actions (B, K, J), thruster_actions (B, K, T)) -> (final states, Trajectory), the
    scenes of the batch stepped side by side (params shared)."""
    return jax.jit(jax.vmap(scan_steps(static, _trajectory), in_axes=(0, None, 0, 0)))


def zero_actions(static: StaticSimParams, num_steps: int = ROLLOUT_STEPS, batch: int | None = None):
    """(motor, thruster) float32 zeros of shape ([batch,] num_steps, J) and ([batch,] num_steps, T)."""
    lead = (num_steps,) if batch is None else (batch, num_steps)
    return np.zeros(lead + (static.num_joints,), np.float32), np.zeros(lead + (static.num_thrusters,), np.float32)


def random_actions(
    rng: np.random.Generator, static: StaticSimParams, num_steps: int = ROLLOUT_STEPS, batch: int | None = None
):
    """(motor, thruster) float32 actions like `zero_actions`, motors uniform in [-1, 1] and thrusters in [0, 1]."""
    lead = (num_steps,) if batch is None else (batch, num_steps)
    motors = rng.uniform(-1.0, 1.0, lead + (static.num_joints,)).astype(np.float32)
    thrusters = rng.uniform(0.0, 1.0, lead + (static.num_thrusters,)).astype(np.float32)
    return motors, thrusters


def run_batch(
    states,
    motor_actions=None,
    thruster_actions=None,
    params: SimParams = PARAMS,
    static: StaticSimParams = BATCH_STATIC,
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
    final, trajectory = _batched_scan(static)(stack(*padded_states), params, motor_actions, thruster_actions)
    trim = lambda tree: jax.tree_util.tree_map(lambda x: np.asarray(x)[:count], tree)  # noqa: E731
    return trim(final), trim(trajectory)


def python_loop(
    state,
    motor_actions,
    thruster_actions,
    params: SimParams = PARAMS,
    static: StaticSimParams = BATCH_STATIC,
):
    """Step one scene with `engine.step` in a Python loop; returns the list of (state, info) after each step."""
    out = []
    for k in range(len(motor_actions)):
        state, info = engine.step(
            state, params, jnp.asarray(motor_actions[k]), jnp.asarray(thruster_actions[k]), static=static
        )
        out.append((state, info))
    return out


# --------------------------------------------------------------------------- long runs of one scene
@dataclasses.dataclass
class Motion:
    """Per-step record of a `run_scene` of n steps (numpy, float64 where float).

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
def _chunk_scan(static: StaticSimParams):
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


def run_scene(state, static: StaticSimParams, steps: int, params: SimParams | None = None, motor=None, thrust=None):
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
        state, record = _chunk_scan(static)(state, params, m, t, count)
        records.append(jax.tree_util.tree_map(lambda x, c=count: np.asarray(x)[:c], record))
    merged = {key: np.concatenate([r[key] for r in records if key in r]) for key in records[-1]}
    merged = {key: value.astype(np.float64) if value.dtype == np.float32 else value for key, value in merged.items()}
    return state, Motion(**merged)


# --------------------------------------------------------------------------- env episodes
@functools.partial(jax.jit, static_argnames=("static", "record"))
def env_episodes(
    levels: env.Level,
    actions: jax.Array,
    params: env.EnvParams,
    static: env.StaticEnvParams,
    record: Callable[[env.EnvState, env.StepResult], object],
):
    """Per-step `record(state after the step, its StepResult)` stacked over (B, T): B levels (stacked) played from
    their starts with (B, T, ...) actions, the env's default action type, auto-reset as in `env.step`."""

    def episode(level, level_actions):
        def one_step(state, action):
            state, result = env.step(state, action, level, params, static)
            return state, record(state, result)

        return jax.lax.scan(one_step, env.reset(level), level_actions)[1]

    return jax.vmap(episode)(levels, actions)


def env_loop(level: env.Level, actions, params: env.EnvParams, static: env.StaticEnvParams, action_type):
    """(states before each step, StepResults), each stacked over T: one level played from its start with (T, ...)
    actions, one call of the jitted `env.step` per action."""
    state, states, results = env.reset(level), [], []
    for action in actions:
        states.append(state)
        state, result = env.step(state, action, level, params, static, action_type)
        results.append(result)
    return stack(*states), stack(*results)
