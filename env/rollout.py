"""Batched first-episode rollouts of a fixed simple policy (no-op or uniform random) on a batch of levels."""

from __future__ import annotations

import enum
import functools

import jax
import jax.numpy as jnp
from flax import struct

from kforge.env.actions import ActionType, noop_action, random_action
from kforge.env.episode import advance, reset
from kforge.env.params import EnvParams, StaticEnvParams
from kforge.env.state import Level


class Outcome(enum.IntEnum):
    """How a level's first episode ended within the rollout."""

    TIMEOUT = 0  # no success, failure or instability within the rollout's steps
    SUCCESS = 1  # green touched blue
    FAILURE = 2  # green touched red
    UNSTABLE = 3  # the simulation produced NaN


class Policy(enum.Enum):
    """The simple policies a rollout can run."""

    NOOP = "noop"
    UNIFORM_RANDOM = "uniform_random"


@struct.dataclass
class RolloutResult:
    """Per-level result of a first-episode rollout, shape (B,)."""

    outcome: jnp.ndarray  # (B,) i32 `Outcome`
    length: jnp.ndarray  # (B,) i32 env steps until the first episode ended; the rollout length if it did not


ROLLOUT_ACTION_TYPE = ActionType.MULTI_DISCRETE
"""The action space a rollout's policy acts in (its no-op or uniform random actions)."""


@functools.partial(jax.jit, static_argnames=("static", "policy", "num_steps"))
def first_episode_outcomes(
    levels: Level,
    params: EnvParams,
    static: StaticEnvParams,
    policy: Policy = Policy.NOOP,
    key: jax.Array | None = None,
    num_steps: int | None = None,
) -> RolloutResult:
    """Run `policy` on every level of the batch for up to `num_steps` env steps (default: a full episode), in
    `ROLLOUT_ACTION_TYPE`'s actions.

    `key` is required for the random policy (a fresh action per level and step). Stops early once every level's
    first episode has ended.
    """
    num_steps = static.max_timesteps if num_steps is None else num_steps
    if not 1 <= num_steps <= static.max_timesteps:
        raise ValueError(f"num_steps must be in [1, {static.max_timesteps}], got {num_steps}")
    if policy is Policy.UNIFORM_RANDOM and key is None:
        raise ValueError("the uniform random policy needs a PRNG key")
    batch = jax.tree.leaves(levels)[0].shape[0]
    step_batch = jax.vmap(advance, in_axes=(0, 0, None, None, None))
    action_type = ROLLOUT_ACTION_TYPE

    def actions(t):
        if policy is Policy.NOOP:
            return jnp.broadcast_to(noop_action(action_type), (batch,) + noop_action(action_type).shape)
        keys = jax.random.split(jax.random.fold_in(key, t), batch)
        return jax.vmap(random_action, in_axes=(0, None))(keys, action_type)

    def running(carry):
        t, _, _, _, done = carry
        return (t < num_steps) & ~jnp.all(done)

    def body(carry):
        t, states, outcome, length, done = carry
        states, result = step_batch(states, actions(t), params, static, action_type)
        ended = result.done & ~done
        this = jnp.where(
            result.success,
            Outcome.SUCCESS,
            jnp.where(result.failure, Outcome.FAILURE, jnp.where(result.unstable, Outcome.UNSTABLE, Outcome.TIMEOUT)),
        )
        outcome = jnp.where(ended, this, outcome)
        length = jnp.where(ended, t + 1, length)
        return t + 1, states, outcome, length, done | result.done

    start = (
        jnp.zeros((), jnp.int32),
        jax.vmap(reset)(levels),
        jnp.full((batch,), Outcome.TIMEOUT, jnp.int32),
        jnp.full((batch,), num_steps, jnp.int32),
        jnp.zeros((batch,), bool),
    )
    _, _, outcome, length, _ = jax.lax.while_loop(running, body, start)
    return RolloutResult(outcome=outcome, length=length)
