"""Masked multi-discrete policy distribution over the env's six action slots.

The actor's 16 logits are split into one categorical per slot (`MULTI_DISCRETE_SIZES` = 3, 3, 3, 3, 2, 2). A slot the
level cannot use (`env.action_mask` False) always takes choice 0 (no-op), adds 0 to the log-probability and nothing to
the entropy, so it neither acts nor receives gradient.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from kforge.env import MULTI_DISCRETE_SIZES

NUM_LOGITS = sum(MULTI_DISCRETE_SIZES)
"""Actor outputs: the concatenated logits of every slot."""

MAX_CHOICES = max(MULTI_DISCRETE_SIZES)

_OFFSETS = np.cumsum((0,) + MULTI_DISCRETE_SIZES[:-1])
_CHOICE = np.arange(MAX_CHOICES)
_GATHER = np.minimum(_OFFSETS[:, None] + _CHOICE[None, :], NUM_LOGITS - 1)  # (6, 3) logit index of each choice
_EXISTS = _CHOICE[None, :] < np.asarray(MULTI_DISCRETE_SIZES)[:, None]  # (6, 3) the slot has this choice

EXCLUDED_LOGIT = -1e9
"""Logit given to choices a slot does not have: probability exactly 0 and finite log-probability."""


def slot_log_probs(logits: jnp.ndarray) -> jnp.ndarray:
    """(..., 6, 3) log-probabilities of each slot's choices from (..., 16) logits; missing choices ~ -1e9."""
    if logits.shape[-1] != NUM_LOGITS:
        raise ValueError(f"expected {NUM_LOGITS} logits in the last axis, got shape {logits.shape}")
    per_slot = jnp.where(_EXISTS, logits[..., _GATHER], EXCLUDED_LOGIT)
    return jax.nn.log_softmax(per_slot, axis=-1)


def sample(key: jax.Array, logits: jnp.ndarray, mask: jnp.ndarray) -> jnp.ndarray:
    """(..., 6) i32 action drawn slot by slot; masked-out slots are 0."""
    choice = jax.random.categorical(key, slot_log_probs(logits), axis=-1)
    return jnp.where(mask, choice, 0).astype(jnp.int32)


def mode(logits: jnp.ndarray, mask: jnp.ndarray) -> jnp.ndarray:
    """(..., 6) i32 most probable choice of every slot; masked-out slots are 0."""
    return jnp.where(mask, jnp.argmax(slot_log_probs(logits), axis=-1), 0).astype(jnp.int32)


def log_prob(logits: jnp.ndarray, action: jnp.ndarray, mask: jnp.ndarray) -> jnp.ndarray:
    """(...,) log-probability of `action` (..., 6): the sum over valid slots of the chosen choice's log-probability."""
    chosen = jnp.take_along_axis(slot_log_probs(logits), action[..., None].astype(jnp.int32), axis=-1)[..., 0]
    return jnp.sum(jnp.where(mask, chosen, 0.0), axis=-1)


def entropy(logits: jnp.ndarray, mask: jnp.ndarray) -> jnp.ndarray:
    """(...,) entropy [nats] of the joint distribution: the sum of the valid slots' entropies."""
    log_p = slot_log_probs(logits)
    per_slot = -jnp.sum(jnp.where(_EXISTS, jnp.exp(log_p) * log_p, 0.0), axis=-1)
    return jnp.sum(jnp.where(mask, per_slot, 0.0), axis=-1)
