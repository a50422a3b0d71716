"""Behaviour cloning's objective: the expert action's negative log-likelihood per action slot, over valid slots only.

A level's `action_mask` marks the slots its actuators use. Each transition's loss is the mean over its valid slots of
the slot's negative log-likelihood (Kinetix's "disentangled" BC loss), so a slot the level cannot use contributes
nothing, whatever its logits; the batch loss is the mean over transitions.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp

from kforge.agents.policy import slot_log_probs


class ImitationTerms(NamedTuple):
    """The BC loss of a batch and its per-slot parts (slot axis of size 6)."""

    loss: jnp.ndarray  # () mean over transitions of the mean valid-slot NLL [nats]
    slot_nll: jnp.ndarray  # (6,) mean NLL of each slot over the transitions where it is valid [nats]
    slot_accuracy: jnp.ndarray  # (6,) share of those transitions whose most probable choice is the expert's
    slot_count: jnp.ndarray  # (6,) transitions where the slot is valid
    accuracy: jnp.ndarray  # () share of all valid (transition, slot) pairs predicted right
    transition_count: jnp.ndarray  # () transitions with at least one valid slot (weighted)


def imitation_terms(
    logits: jnp.ndarray, action: jnp.ndarray, action_mask: jnp.ndarray, weight: jnp.ndarray | None = None
) -> ImitationTerms:
    """BC terms of logits (..., 16) against expert actions (..., 6) under the levels' masks (..., 6).

    `weight` (...,) scales each transition's share (default 1; 0 leaves a padding transition out).
    """
    log_p = slot_log_probs(logits)
    chosen = jnp.take_along_axis(log_p, action[..., None].astype(jnp.int32), axis=-1)[..., 0]
    valid = action_mask.astype(bool)
    weight = jnp.ones(action.shape[:-1], jnp.float32) if weight is None else weight.astype(jnp.float32)
    slot_weight = valid.astype(jnp.float32) * weight[..., None]
    nll = jnp.where(valid, -chosen, 0.0)
    valid_slots = jnp.sum(valid, axis=-1)
    per_transition = jnp.sum(nll, axis=-1) / jnp.maximum(valid_slots, 1)
    counted = (valid_slots > 0).astype(jnp.float32) * weight
    batch_axes = tuple(range(action.ndim - 1))
    correct = (jnp.argmax(log_p, axis=-1) == action).astype(jnp.float32) * slot_weight
    slot_count = jnp.sum(slot_weight, axis=batch_axes)
    return ImitationTerms(
        loss=jnp.sum(per_transition * counted) / jnp.maximum(jnp.sum(counted), 1.0),
        slot_nll=jnp.sum(nll * slot_weight, axis=batch_axes) / jnp.maximum(slot_count, 1.0),
        slot_accuracy=jnp.sum(correct, axis=batch_axes) / jnp.maximum(slot_count, 1.0),
        slot_count=slot_count,
        accuracy=jnp.sum(correct) / jnp.maximum(jnp.sum(slot_weight), 1.0),
        transition_count=jnp.sum(counted),
    )
