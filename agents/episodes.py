"""Evaluation of trained specialists: K episodes per level from its start or from any stored episode state."""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp

from kforge.agents import policy
from kforge.agents.batching import ACTION_TYPE, check_level_keys, num_levels
from kforge.agents.config import PPOConfig
from kforge.agents.networks import make_network
from kforge.env import EnvParams, EnvState, Level, StaticEnvParams, action_mask, advance, observe, reset


class EvalOutput(NamedTuple):
    """Per-level evaluation results (leading axis L; per-episode fields (L, K))."""

    success_rate: jnp.ndarray  # (L,) f32 share of the K episodes that ended in success
    mean_return: jnp.ndarray  # (L,) f32 undiscounted return from the start state, averaged over episodes
    mean_length: jnp.ndarray  # (L,) f32 [env steps] taken from the start state until the episode ended
    success: jnp.ndarray  # (L, K) bool
    returns: jnp.ndarray  # (L, K) f32
    lengths: jnp.ndarray  # (L, K) i32


class Episode(NamedTuple):
    """How an episode ended (state, success, failure, return and length once finished)."""

    state: EnvState
    finished: jnp.ndarray  # () bool
    success: jnp.ndarray  # () bool: green touched blue
    failure: jnp.ndarray  # () bool: green touched red
    episode_return: jnp.ndarray  # () f32
    length: jnp.ndarray  # () i32


Actor = Callable[[EnvState, jnp.ndarray, jax.Array], jnp.ndarray]
"""A policy as a function (state, action mask (6,), PRNG key) -> multi-discrete action (6,) i32."""


def run_episode(act: Actor, start: EnvState, mask: jnp.ndarray, key: jax.Array, env_params, static) -> Episode:
    """One episode of `act` from `start` until it ends (at most `static.max_timesteps` steps); no reset."""

    def step(episode: Episode, step_key):
        action = act(episode.state, mask, step_key)
        reached, result = advance(episode.state, action, env_params, static, ACTION_TYPE)
        running = ~episode.finished
        following = Episode(
            state=reached,
            finished=result.done,
            success=result.success,
            failure=result.failure,
            episode_return=episode.episode_return + result.reward,
            length=episode.length + 1,
        )
        return jax.tree.map(lambda new, old: jnp.where(running, new, old), following, episode), None

    first = Episode(
        state=start,
        finished=jnp.zeros((), bool),
        success=jnp.zeros((), bool),
        failure=jnp.zeros((), bool),
        episode_return=jnp.zeros((), jnp.float32),
        length=jnp.zeros((), jnp.int32),
    )
    episode, _ = jax.lax.scan(step, first, jax.random.split(key, static.max_timesteps))
    return episode


def network_actor(network, params, observation_type, static: StaticEnvParams, greedy: bool) -> Actor:
    """The actor of a logits network (`network.apply(params, obs)` returns logits first, or only logits)."""

    def act(state: EnvState, mask: jnp.ndarray, key: jax.Array) -> jnp.ndarray:
        out = network.apply(params, observe(state, static, observation_type))
        logits = out[0] if isinstance(out, tuple) else out
        return policy.mode(logits, mask) if greedy else policy.sample(key, logits, mask)

    return act


@dataclasses.dataclass(frozen=True)
class EpisodePlan:
    """How the PPO policy plays a level's evaluation episodes: its network (`config`), the env's static size, the
    episodes per level, and whether it takes its most probable action per slot (`greedy`) or samples."""

    config: PPOConfig
    static: StaticEnvParams
    num_episodes: int
    greedy: bool = False


def _run_episode(params, start: EnvState, mask: jnp.ndarray, key: jax.Array, plan: EpisodePlan, env_params) -> Episode:
    """One episode of the PPO policy with `params` from `start`."""
    act = network_actor(make_network(plan.config), params, plan.config.observation_type, plan.static, plan.greedy)
    return run_episode(act, start, mask, key, env_params, plan.static)


def evaluate(
    params,
    levels: Level,
    keys: jax.Array,
    plan: EpisodePlan,
    env_params: EnvParams,
    start_states: EnvState | None = None,
) -> EvalOutput:
    """Run `plan.num_episodes` episodes per level with that level's parameters (leading axis L on params and levels).

    Episodes start from `start_states` (batched `EnvState`, e.g. mid-trajectory) or, when None, from each level's
    start; they run until success, failure, instability or the time limit, with no reset. Actions are sampled from
    the policy, or its most probable choice per slot when `plan.greedy`. `keys`: one PRNG key per level.
    """
    check_level_keys(keys, num_levels(levels))
    if plan.num_episodes < 1:
        raise ValueError(f"num_episodes must be >= 1, got {plan.num_episodes}")
    if start_states is None:
        start_states = jax.vmap(reset)(levels)
    return _evaluate(params, levels, start_states, keys, plan, env_params)


def level_episodes(
    params, level: Level, start: EnvState, key: jax.Array, plan: EpisodePlan, env_params: EnvParams
) -> Episode:
    """`plan.num_episodes` episodes of one level (no level axis) from `start`: an `Episode` with leaves
    (num_episodes,).

    Pure and traceable, so training evaluates its checkpoints with it inside the training program.
    """
    run = functools.partial(_run_episode, params, start, action_mask(level), plan=plan, env_params=env_params)
    return jax.vmap(run)(jax.random.split(key, plan.num_episodes))


@functools.partial(jax.jit, static_argnames=("plan",))
def _evaluate(params, levels, start_states, keys, plan: EpisodePlan, env_params) -> EvalOutput:
    episodes = jax.vmap(
        lambda level_params, level, start, key: level_episodes(level_params, level, start, key, plan, env_params)
    )(params, levels, start_states, keys)
    return EvalOutput(
        success_rate=jnp.mean(episodes.success.astype(jnp.float32), axis=1),
        mean_return=jnp.mean(episodes.episode_return, axis=1),
        mean_length=jnp.mean(episodes.length.astype(jnp.float32), axis=1),
        success=episodes.success,
        returns=episodes.episode_return,
        lengths=episodes.length,
    )
