"""Actor-critic on flat observations: separate tanh MLPs for the policy logits and the value (Kinetix layout), or a
behaviour-cloning policy network as the actor beside the same critic, so that PPO can fine-tune a BC policy."""

from __future__ import annotations

import math

import flax.linen as nn
import jax
import jax.numpy as jnp

from kforge.agents.bc_networks import NetworkConfig, make_bc_network
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


BC_ACTOR = "bc_actor"
"""Name of a BC actor's parameters in `BCActorCritic`'s tree (`params["params"][BC_ACTOR]`)."""


def _critic(obs: jnp.ndarray, hidden_size: int, num_hidden_layers: int) -> jnp.ndarray:
    for layer in range(num_hidden_layers):
        obs = nn.tanh(_dense(hidden_size, HIDDEN_INIT_SCALE, f"critic_hidden_{layer}")(obs))
    return _dense(1, CRITIC_OUTPUT_INIT_SCALE, "critic_output")(obs)[..., 0]


class ActorCritic(nn.Module):
    """obs (..., D) -> (logits (..., 16), value (...)); actor and critic share no parameters."""

    hidden_size: int
    num_hidden_layers: int

    @nn.compact
    def __call__(self, obs: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
        actor = obs
        for layer in range(self.num_hidden_layers):
            actor = nn.tanh(_dense(self.hidden_size, HIDDEN_INIT_SCALE, f"actor_hidden_{layer}")(actor))
        logits = _dense(NUM_LOGITS, ACTOR_OUTPUT_INIT_SCALE, "actor_output")(actor)
        return logits, _critic(obs, self.hidden_size, self.num_hidden_layers)


class BCActorCritic(nn.Module):
    """obs (..., D) -> (logits (..., 16), value (...)): the BC policy network `actor` (its parameters under
    `BC_ACTOR`, as `make_bc_network(actor)` initialises them) beside `ActorCritic`'s critic."""

    actor: NetworkConfig
    hidden_size: int
    num_hidden_layers: int

    @nn.compact
    def __call__(self, obs: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
        logits = make_bc_network(self.actor, name=BC_ACTOR)(obs)
        return logits, _critic(obs, self.hidden_size, self.num_hidden_layers)


def make_network(config: PPOConfig) -> ActorCritic | BCActorCritic:
    """The actor-critic sized by `config`: with a BC network as the actor when `config.actor` names one."""
    if config.actor is None:
        return ActorCritic(hidden_size=config.hidden_size, num_hidden_layers=config.num_hidden_layers)
    return BCActorCritic(actor=config.actor, hidden_size=config.hidden_size, num_hidden_layers=config.num_hidden_layers)


def with_bc_actor(params, bc_params):
    """`BCActorCritic` parameters `params` with the actor's replaced by a trained BC policy's `bc_params` (as
    `make_bc_network(...).init` shapes them): the start of PPO fine-tuning from behaviour cloning."""
    if BC_ACTOR not in params["params"]:
        raise ValueError(f"these parameters have no {BC_ACTOR!r} network: PPOConfig.actor must name the BC network")
    actor = params["params"][BC_ACTOR]
    given = bc_params["params"]
    if jax.tree.structure(actor) != jax.tree.structure(given) or any(
        a.shape != b.shape for a, b in zip(jax.tree.leaves(actor), jax.tree.leaves(given), strict=True)
    ):
        raise ValueError(
            "the BC policy's parameters do not fit PPOConfig.actor's network (another architecture or size)"
        )
    return {**params, "params": {**params["params"], BC_ACTOR: given}}
