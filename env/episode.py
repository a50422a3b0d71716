"""Pure episode functions: `reset(level)` and `step(state, action, level)` with same-level auto-reset."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from flax import struct

from kforge.engine import step as physics_step
from kforge.env.actions import ActionType, actuator_actions
from kforge.env.params import EnvParams, StaticEnvParams
from kforge.env.rewards import goal_reward, green_blue_distance
from kforge.env.state import NO_DISTANCE, EnvState, Level, initial_state


@struct.dataclass
class StepResult:
    """What one env step produced, besides the next state."""

    reward: jnp.ndarray  # () f32 goal reward (first decisive physics step) plus dense shaping
    done: jnp.ndarray  # () bool: the episode ended; the returned state is already the level's start
    success: jnp.ndarray  # () bool: ended because green touched blue (never set together with failure)
    failure: jnp.ndarray  # () bool: ended because green touched red
    unstable: jnp.ndarray  # () bool: ended because the simulation produced NaN
    truncated: jnp.ndarray  # () bool: ended by the time limit without success or failure
    distance: jnp.ndarray  # () f32 [m] green-blue distance after the step (before any reset)


def reset(level: Level) -> EnvState:
    """The start of an episode on `level`."""
    return initial_state(level)


def _has_nan(tree) -> jnp.ndarray:
    leaves = [jnp.any(jnp.isnan(x)) for x in jax.tree.leaves(tree) if jnp.issubdtype(x.dtype, jnp.floating)]
    return jnp.any(jnp.stack(leaves))


def advance(
    state: EnvState, action: jnp.ndarray, params: EnvParams, static: StaticEnvParams, action_type: ActionType
) -> tuple[EnvState, StepResult]:
    """One env step without auto-reset: `frame_skip` physics steps with the same action, reward and termination."""
    motor, thruster = actuator_actions(state, action, action_type)

    def physics(carry, _):
        sim, decided, reward = carry
        sim, info = physics_step(sim, params.sim, motor, thruster, static=static.sim)
        step_reward = goal_reward(info.touching, state.task, sim.bodies.active, static.sim)
        reward = jnp.where(decided, reward, step_reward)
        return (sim, decided | (step_reward != 0.0), reward), None

    start = (state.sim, jnp.zeros((), bool), jnp.zeros((), jnp.float32))
    (sim, decided, goal), _ = jax.lax.scan(physics, start, None, length=static.frame_skip)

    distance = green_blue_distance(sim.bodies.position, sim.bodies.active, state.task)
    shaping = jnp.where(
        (state.last_distance == NO_DISTANCE) | (params.dense_reward_scale == 0.0),
        0.0,
        -(distance - state.last_distance) * params.dense_reward_scale,
    )
    timestep = state.timestep + 1
    unstable = _has_nan(sim)
    shaping = jnp.where(unstable, 0.0, shaping)
    timeout = timestep >= static.max_timesteps
    done = decided | unstable | timeout
    result = StepResult(
        reward=(goal + shaping).astype(jnp.float32),
        done=done,
        success=decided & (goal > 0.0),
        failure=decided & (goal < 0.0),
        unstable=unstable & ~decided,
        truncated=timeout & ~decided & ~unstable,
        distance=distance,
    )
    next_state = state.replace(
        sim=sim, timestep=timestep, last_distance=jnp.where(done, NO_DISTANCE, distance).astype(jnp.float32)
    )
    return next_state, result


@functools.partial(jax.jit, static_argnames=("static", "action_type"))
def step(
    state: EnvState,
    action: jnp.ndarray,
    level: Level,
    params: EnvParams,
    static: StaticEnvParams,
    action_type: ActionType = ActionType.MULTI_DISCRETE,
) -> tuple[EnvState, StepResult]:
    """One env step; when the episode ends the returned state is `level`'s start (auto-reset to the same level).

    The reset is a selection between two states already in hand, so it costs no simulation.
    """
    stepped, result = advance(state, action, params, static, action_type)
    start = reset(level)
    next_state = jax.tree.map(lambda fresh, old: jnp.where(result.done, fresh, old), start, stepped)
    return next_state, result
