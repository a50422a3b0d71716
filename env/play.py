"""Playing a level with a simple policy as one compiled program: the states and step results of an episode, for a
GIF (`kforge render`, `kforge levels preview`)."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from kforge.env.actions import ActionType, noop_action, random_action
from kforge.env.episode import StepResult, reset, step
from kforge.env.params import EnvParams, StaticEnvParams
from kforge.env.rollout import Policy
from kforge.env.state import EnvState, Level


@functools.partial(jax.jit, static_argnames=("static", "policy", "num_steps"))
def record_episode(
    level: Level, params: EnvParams, static: StaticEnvParams, policy: Policy, key: jax.Array, num_steps: int
) -> tuple[EnvState, StepResult]:
    """States (num_steps + 1, ...) from the level's start and step results (num_steps,) under `policy`.

    Episodes that end are followed by the level's start again (auto-reset), as the dataset records them.
    """

    def body(state, step_key):
        if policy is Policy.NOOP:
            action = noop_action(ActionType.MULTI_DISCRETE)
        else:
            action = random_action(step_key, ActionType.MULTI_DISCRETE)
        next_state, result = step(state, action, level, params, static)
        return next_state, (next_state, result)

    start = reset(level)
    _, (states, results) = jax.lax.scan(body, start, jax.random.split(key, num_steps))
    states = jax.tree.map(lambda first, rest: jnp.concatenate([first[None], rest]), start, states)
    return states, results
