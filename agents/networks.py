"""Actor-critic on flat observations: separate tanh MLPs for the policy logits and the value (Kinetix layout)."""

from __future__ import annotations

import math

import flax.linen as nn
import jax.numpy as jnp

from kforge.agents.config import PPOConfig
from kforge.agents.policy import NUM_LOGITS

HIDDEN_INIT_SCALE = math.sqrt(2.0)
"""Orthogonal-init gain of hidden layers."""

ACTOR_OUTPUT_INIT_SCALE = 0.01
"""Orthogonal-init gain of the logits layer: a near-uniform initial policy."""

CRITIC_OUTPUT_INIT_SCALE = 1.0
"""Orthogonal-init gain of the value layer."""


def _dense(features: int, scale: float, name: str) -> nn.Dense:
    return nn.Dense(features, kernel_init=nn.initializers.orthogonal(scale), bias_init=nn.initializers.zeros, name=name)


class ActorCritic(nn.Module):
    """obs (..., D) -> (logits (..., 16), value (...)); actor and critic share no parameters."""

    hidden_size: int
    num_hidden_layers: int

    @nn.compact
    def __call__(self, obs: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
        actor, critic = obs, obs
        for layer in range(self.num_hidden_layers):
            actor = nn.tanh(_dense(self.hidden_size, HIDDEN_INIT_SCALE, f"actor_hidden_{layer}")(actor))
            critic = nn.tanh(_dense(self.hidden_size, HIDDEN_INIT_SCALE, f"critic_hidden_{layer}")(critic))
        logits = _dense(NUM_LOGITS, ACTOR_OUTPUT_INIT_SCALE, "actor_output")(actor)
        value = _dense(1, CRITIC_OUTPUT_INIT_SCALE, "critic_output")(critic)[..., 0]
        return logits, value


def make_network(config: PPOConfig) -> ActorCritic:
    """The actor-critic sized by `config`."""
    return ActorCritic(hidden_size=config.hidden_size, num_hidden_layers=config.num_hidden_layers)
