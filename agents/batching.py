"""What every agent program shares: the action space agents act in and checks of batched levels and their keys."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from kforge.env import ActionType, Level

ACTION_TYPE = ActionType.MULTI_DISCRETE
"""The action space the agents act in."""


def num_levels(levels: Level) -> int:
    """The size of the leading level axis of a batched `Level`; errors when the leaves disagree."""
    sizes = {x.shape[0] if x.ndim else None for x in jax.tree.leaves(levels)}
    if len(sizes) != 1 or None in sizes:
        raise ValueError(f"levels must be a batched Level with one leading level axis; leading sizes {sizes}")
    return sizes.pop()


def check_level_keys(keys: jax.Array, count: int) -> None:
    """Errors unless `keys` holds one PRNG key per level."""
    typed = jnp.issubdtype(keys.dtype, jax.dtypes.prng_key)
    shape_ok = keys.shape == (count,) if typed else keys.shape == (count, 2)
    if not shape_ok:
        raise ValueError(
            f"expected one PRNG key per level ({count} levels): shape ({count},) typed or ({count}, 2) raw uint32 "
            f"keys, got shape {keys.shape} dtype {keys.dtype}"
        )
