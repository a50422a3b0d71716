"""Run a rank-polymorphic function with batch axes last when it is vmapped.

On CPU, XLA vectorises across the minor (last) axis. A function written so that every array keeps its
per-scene axes first and carries any number of trailing batch axes can therefore be vmapped much faster
by moving the vmapped axis to the end than by JAX's default (batch axis first).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def vmap_batch_last(function):
    """`function` with a vmap rule that moves the batch axis of every argument to the end.

    `function` must accept arrays with arbitrary trailing batch axes (never index, reduce or concatenate
    from the end). Unbatched arguments are broadcast along the new trailing axis; outputs are batched.
    """
    wrapped = jax.custom_batching.custom_vmap(function)

    @wrapped.def_vmap
    def rule(axis_size, in_batched, *args):
        def to_last(x, batched):
            x = jnp.asarray(x)
            if batched:
                return jnp.moveaxis(x, 0, -1)
            return jnp.broadcast_to(x[..., None], x.shape + (axis_size,))

        moved = jax.tree_util.tree_map(to_last, args, tuple(in_batched))
        out = wrapped(*moved)
        out = jax.tree_util.tree_map(lambda x: jnp.moveaxis(x, -1, 0), out)
        return out, jax.tree_util.tree_map(lambda _: True, out)

    return wrapped
