"""Expert windows for the dataset: a fixed number of env steps per level with auto-reset, states recorded."""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp

from kforge.agents import policy
from kforge.agents.batching import ACTION_TYPE, check_level_keys, num_levels
from kforge.agents.config import PPOConfig
from kforge.agents.networks import make_network
from kforge.env import EnvParams, EnvState, Level, StaticEnvParams, action_mask, observe, reset, step

WINDOW_STEPS = 256
"""Env steps per stored trajectory (one Kinetix episode length)."""


class Window(NamedTuple):
    """A rollout window per level (leading axis L; per-step fields (L, W, ...))."""

    states: EnvState  # (L, W, ...) state before each action (auto-reset starts appear after an episode end)
    actions: jnp.ndarray  # (L, W, 6) i32 multi-discrete actions taken
    action_mask: jnp.ndarray  # (L, 6) bool valid action slots of the level
    done: jnp.ndarray  # (L, W) bool: the episode ended with this step
    success: jnp.ndarray  # (L, W) bool: the episode ended with this step in success
    rewards: jnp.ndarray  # (L, W) f32
    episodes_ended: jnp.ndarray  # (L,) i32 episode ends inside the window
    successes: jnp.ndarray  # (L,) i32 of which successes
    successful: jnp.ndarray  # (L,) bool: at least one episode ended and every ending was a success


@dataclasses.dataclass(frozen=True)
class WindowPlan:
    """How the expert plays a level's window: its network (`config`), the env's static size, the env steps, and
    whether it takes its most probable action per slot (`greedy`) or samples."""

    config: PPOConfig
    static: StaticEnvParams
    num_steps: int = WINDOW_STEPS
    greedy: bool = False


def collect_windows(params, levels: Level, keys: jax.Array, plan: WindowPlan, env_params: EnvParams) -> Window:
    """Roll each level's expert (leading axis L on params and levels) for `plan.num_steps` env steps from the start.

    Episodes that end are followed by the level's start (auto-reset), so a window may hold several episodes.
    Actions are sampled from the policy, or its most probable choice per slot when `plan.greedy`; one key per level.
    """
    check_level_keys(keys, num_levels(levels))
    if plan.num_steps < 1:
        raise ValueError(f"num_steps must be >= 1, got {plan.num_steps}")
    return _collect(params, levels, keys, plan, env_params)


@functools.partial(jax.jit, static_argnames=("plan",))
def _collect(params, levels, keys, plan: WindowPlan, env_params) -> Window:
    return jax.vmap(functools.partial(_level_window, plan=plan, env_params=env_params))(params, levels, keys)


def _level_window(level_params, level: Level, key: jax.Array, plan: WindowPlan, env_params: EnvParams) -> Window:
    """One level's window: `plan.num_steps` env steps with auto-reset from the level's start."""
    network = make_network(plan.config)
    mask = action_mask(level)

    def body(state: EnvState, step_key):
        logits, _ = network.apply(level_params, observe(state, plan.static, plan.config.observation_type))
        action = policy.mode(logits, mask) if plan.greedy else policy.sample(step_key, logits, mask)
        following, result = step(state, action, level, env_params, plan.static, ACTION_TYPE)
        return following, (state, action, result.done, result.success, result.reward)

    _, (states, actions, done, success, rewards) = jax.lax.scan(
        body, reset(level), jax.random.split(key, plan.num_steps)
    )
    ended, succeeded = jnp.sum(done, dtype=jnp.int32), jnp.sum(success, dtype=jnp.int32)
    return Window(
        states=states,
        actions=actions,
        action_mask=mask,
        done=done,
        success=success,
        rewards=rewards,
        episodes_ended=ended,
        successes=succeeded,
        successful=(ended > 0) & (succeeded == ended),
    )
