"""A gymnax-style view of one env configuration: size, action space and observation type bound together."""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp

from kforge.env.actions import ActionType, noop_action, random_action
from kforge.env.actions import action_mask as level_action_mask
from kforge.env.episode import StepResult, reset, step
from kforge.env.observations import ObservationType, observe
from kforge.env.params import EnvParams, StaticEnvParams
from kforge.env.state import EnvState, Level


@dataclasses.dataclass(frozen=True)
class Environment:
    """Pure `reset` / `step` returning observations; hashable, so methods jit with the instance static.

    `step` auto-resets to the `level` it is given, the pattern per-level experts need.
    """

    static: StaticEnvParams
    action_type: ActionType = ActionType.MULTI_DISCRETE
    observation_type: ObservationType = ObservationType.SYMBOLIC_FLAT

    @classmethod
    def for_size(cls, size: str, **kwargs) -> Environment:
        """The environment of Kinetix size 's', 'm' or 'l'."""
        return cls(static=StaticEnvParams.for_size(size), **kwargs)

    @functools.partial(jax.jit, static_argnums=0)
    def reset(self, level: Level) -> tuple[jnp.ndarray, EnvState]:
        """Observation and state at the start of `level`."""
        state = reset(level)
        return self.observe(state), state

    @functools.partial(jax.jit, static_argnums=0)
    def step(
        self, state: EnvState, action: jnp.ndarray, level: Level, params: EnvParams
    ) -> tuple[jnp.ndarray, EnvState, StepResult]:
        """Observation, next state (the level's start after `done`) and what the step produced."""
        state, result = step(state, action, level, params, self.static, self.action_type)
        return self.observe(state), state, result

    def observe(self, state: EnvState):
        """The observation of `state` (any stored state can be re-observed)."""
        return observe(state, self.static, self.observation_type)

    def action_mask(self, level: Level | EnvState) -> jnp.ndarray:
        """(6,) bool: the unified action slots that can influence `level`."""
        return level_action_mask(level)

    def noop_action(self) -> jnp.ndarray:
        return noop_action(self.action_type)

    def random_action(self, key: jax.Array) -> jnp.ndarray:
        return random_action(key, self.action_type)
