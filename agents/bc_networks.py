"""Policies for behaviour cloning: an MLP over symbolic flat observations, and a permutation-invariant transformer over
symbolic entity observations (Kinetix's offline BC uses entity observations with a small transformer: 128-wide entity
embeddings, attention through a narrow 16-wide query/key/value projection and a linear per-token layer, no MLP).

Both map an observation with any leading axes to the 16 logits of the multi-discrete action (`agents.policy`).
"""

from __future__ import annotations

import dataclasses
import enum
import math

import flax.linen as nn
import jax
import jax.numpy as jnp

from kforge.agents.policy import NUM_LOGITS
from kforge.env import EntityObservation, ObservationType

LOGITS_INIT_SCALE = 0.01
"""Variance-scaling gain of the logits layer: a near-uniform initial policy."""
MASKED_SCORE = -1e9
"""Attention score of an inactive key: its softmax weight is exactly 0 next to any active key."""


class Architecture(enum.Enum):
    """The BC policy's network; each reads one observation type."""

    MLP = "mlp"
    TRANSFORMER = "transformer"

    @property
    def observation_type(self) -> ObservationType:
        if self is Architecture.MLP:
            return ObservationType.SYMBOLIC_FLAT
        return ObservationType.SYMBOLIC_ENTITY


@dataclasses.dataclass(frozen=True)
class NetworkConfig:
    """Sizes of a BC policy network (hashable: a static argument of compiled programs)."""

    architecture: Architecture = Architecture.TRANSFORMER
    hidden_size: int = 256  # MLP: units per hidden layer; transformer: units of the head after pooling
    num_hidden_layers: int = 3  # MLP: hidden layers
    embed_size: int = 128  # transformer: entity embedding width
    num_heads: int = 4  # transformer: attention heads; divides attention_size
    num_layers: int = 2  # transformer: attention blocks
    attention_size: int = 16  # transformer: query/key/value width over all heads (Kinetix's transformer_size: 16)

    def __post_init__(self):
        for name in ("hidden_size", "num_hidden_layers", "embed_size", "num_heads", "num_layers", "attention_size"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.attention_size % self.num_heads:
            raise ValueError(f"num_heads ({self.num_heads}) must divide attention_size ({self.attention_size})")


def _logits_layer() -> nn.Dense:
    return nn.Dense(NUM_LOGITS, kernel_init=nn.initializers.variance_scaling(LOGITS_INIT_SCALE, "fan_in", "normal"))


class MLPPolicy(nn.Module):
    """Symbolic flat observation (..., D) -> logits (..., 16): ReLU MLP."""

    hidden_size: int
    num_hidden_layers: int

    @nn.compact
    def __call__(self, obs: jnp.ndarray) -> jnp.ndarray:
        x = obs
        for _ in range(self.num_hidden_layers):
            x = nn.relu(nn.Dense(self.hidden_size)(x))
        return _logits_layer()(x)


def _gather_rows(rows: jnp.ndarray, indexes: jnp.ndarray) -> jnp.ndarray:
    """rows (..., N, E) at indexes (..., M) -> (..., M, E), as a one-hot product (its gradient is a product too, not
    a scatter)."""
    return jnp.einsum("...mn,...ne->...me", jax.nn.one_hot(indexes, rows.shape[-2], dtype=rows.dtype), rows)


class _Attention(nn.Module):
    """Multi-head self-attention of a few tokens (..., N, E) over the active ones, through `size`-wide queries, keys
    and values. Scores and weighted sums are written as broadcast products over the N x N pairs: with N about 10 and
    heads a few units wide, they fuse into one loop each instead of many tiny matrix products."""

    num_heads: int
    size: int

    @nn.compact
    def __call__(self, tokens: jnp.ndarray, mask: jnp.ndarray) -> jnp.ndarray:
        head = self.size // self.num_heads
        qkv = nn.Dense(3 * self.size)(tokens).reshape(tokens.shape[:-1] + (3, self.num_heads, head))
        query, key, value = qkv[..., 0, :, :], qkv[..., 1, :, :], qkv[..., 2, :, :]  # (..., N, H, D)
        scores = jnp.sum(query[..., :, None, :, :] * key[..., None, :, :, :], axis=-1) / math.sqrt(head)
        scores = jnp.where(mask[..., None, :, None], scores, MASKED_SCORE)  # (..., query, key, H)
        weights = jax.nn.softmax(scores, axis=-2)
        mixed = jnp.sum(weights[..., None] * value[..., None, :, :, :], axis=-3)  # (..., N, H, D)
        return nn.Dense(tokens.shape[-1])(mixed.reshape(tokens.shape[:-1] + (self.size,)))


class _Block(nn.Module):
    """Pre-norm self-attention over the entity tokens, then a linear per-token layer, both residual (Kinetix's
    transformer layer without its optional MLP)."""

    num_heads: int
    attention_size: int

    @nn.compact
    def __call__(self, tokens: jnp.ndarray, mask: jnp.ndarray) -> jnp.ndarray:
        tokens = tokens + _Attention(self.num_heads, self.attention_size)(nn.LayerNorm()(tokens), mask)
        return tokens + nn.Dense(tokens.shape[-1])(nn.LayerNorm()(tokens))


class EntityTransformerPolicy(nn.Module):
    """Symbolic entity observation (leaves with any leading axes) -> logits (..., 16).

    Shapes, joints and thrusters become tokens through one embedding per kind; a joint's token also carries the
    embeddings of the two shapes it connects and a thruster's that of its shape. Attention runs over active tokens
    only, and a masked mean pools them, so the logits do not depend on the order of the entities.
    """

    embed_size: int
    num_heads: int
    num_layers: int
    hidden_size: int
    attention_size: int

    @nn.compact
    def __call__(self, obs: EntityObservation) -> jnp.ndarray:
        embed = self.embed_size
        shapes = jnp.concatenate([nn.Dense(embed)(obs.polygons), nn.Dense(embed)(obs.circles)], axis=-2)
        joints = (
            nn.Dense(embed)(obs.joints)
            + nn.Dense(embed, use_bias=False)(_gather_rows(shapes, obs.joint_indexes[..., 0]))
            + nn.Dense(embed, use_bias=False)(_gather_rows(shapes, obs.joint_indexes[..., 1]))
        )
        thrusters = nn.Dense(embed)(obs.thrusters) + nn.Dense(embed, use_bias=False)(
            _gather_rows(shapes, obs.thruster_indexes)
        )
        tokens = jnp.concatenate([shapes, joints, thrusters], axis=-2)
        mask = jnp.concatenate([obs.polygon_mask, obs.circle_mask, obs.joint_mask, obs.thruster_mask], axis=-1)
        for _ in range(self.num_layers):
            tokens = _Block(self.num_heads, self.attention_size)(tokens, mask)
        tokens = nn.LayerNorm()(tokens)
        weight = mask.astype(tokens.dtype)[..., None]
        pooled = jnp.sum(tokens * weight, axis=-2) / jnp.maximum(jnp.sum(weight, axis=-2), 1.0)
        return _logits_layer()(nn.relu(nn.Dense(self.hidden_size)(pooled)))


def make_bc_network(config: NetworkConfig, name: str | None = None) -> nn.Module:
    """The BC policy network that `config` describes (named `name` inside a parent module)."""
    if config.architecture is Architecture.MLP:
        return MLPPolicy(hidden_size=config.hidden_size, num_hidden_layers=config.num_hidden_layers, name=name)
    return EntityTransformerPolicy(
        embed_size=config.embed_size,
        num_heads=config.num_heads,
        num_layers=config.num_layers,
        hidden_size=config.hidden_size,
        attention_size=config.attention_size,
        name=name,
    )
