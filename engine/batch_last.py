"""Run a rank-polymorphic function with batch axes last when it is vmapped.

On CPU, XLA vectorises across the minor (last) axis. A function written so that every array keeps its
per-scene axes first and carries any number of trailing batch axes can therefore be vmapped much faster
by moving the vmapped axis to the end than by JAX's default (batch axis first).

`vmap_in_chunks` makes a function run large batches in chunks, one after another, so that a chunk's working
set stays in cache.

Both pay only on CPU. On a GPU or TPU one vmapped program over the whole batch is faster: a chunk loop runs the
step's kernels once per chunk in sequence, and the batch-first layout is the one those backends tile well. The
same holds for the solver's loops (its substeps and Gauss-Seidel sweeps, `engine.sweep.SWEEPS`): looped on CPU,
where a loop body compiled once runs fastest, unrolled elsewhere, where each kernel launch costs microseconds
whatever the batch and the unrolled step runs about half the kernels. `Batching`, a static option of each step
(`engine.StaticSimParams.batching`), chooses; its default "auto" picks by `jax.default_backend()` when a step is
traced.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

BATCH_CHUNK = 256
"""Most scenes per call under `vmap_in_chunks`: larger batches are split into equal chunks of at most this many."""

BATCHING_MODES = ("auto", "chunked", "whole")
"""auto: chunked on CPU, whole elsewhere; chunked: batch-last layout and chunks of at most `chunk_limit` scenes;
whole: one ordinary `jax.vmap` over the whole batch."""

CHUNKED_BACKENDS = ("cpu",)
"""Backends on which "auto" chunks (where chunking and the batch-last layout were measured to pay)."""

SOLVER_LOOP_FORMS = ("looped", "unrolled_sweeps", "unrolled")
"""Forms of the solver's loops (substeps, passes and the Gauss-Seidel sweeps of `engine.sweep.SWEEPS`): "looped",
each a `lax.scan` whose body is compiled once; "unrolled_sweeps", the sweeps over contact colours and joints written
out in order inside looped substeps and passes (most of the kernels saved, about half the compile time); or
"unrolled", everything written out."""

SOLVER_LOOP_MODES = ("auto", *SOLVER_LOOP_FORMS)
"""auto: "looped" on `LOOPED_SOLVER_BACKENDS`, "unrolled" elsewhere; or one of `SOLVER_LOOP_FORMS`."""

LOOPED_SOLVER_BACKENDS = ("cpu",)
"""Backends on which "auto" keeps the solver's loops (unrolled, XLA's CPU backend recomputes each item's solve in
every fused consumer: 0.67x the steps/s of s at 256 scenes, 0.57x at 1, and compiles 2-10x longer)."""


@dataclasses.dataclass(frozen=True)
class Batching:
    """How a vmapped step batches (one of `BATCHING_MODES`), the chunk limit in scenes, and the form of the solver's
    loops (one of `SOLVER_LOOP_MODES`): a static option of a step (`engine.StaticSimParams.batching`), so each
    compiled program holds one form. Every choice gives the same states to rounding."""

    mode: str = "auto"
    chunk_limit: int = BATCH_CHUNK
    solver_loops: str = "auto"

    def __post_init__(self):
        if self.mode not in BATCHING_MODES:
            raise ValueError(f"batching mode {self.mode!r} is not one of {BATCHING_MODES}")
        if isinstance(self.chunk_limit, bool) or not isinstance(self.chunk_limit, int) or self.chunk_limit < 1:
            raise ValueError(f"batching chunk_limit must be a positive number of scenes, got {self.chunk_limit!r}")
        if self.solver_loops not in SOLVER_LOOP_MODES:
            raise ValueError(f"solver_loops mode {self.solver_loops!r} is not one of {SOLVER_LOOP_MODES}")

    def resolved(self, backend: str | None = None) -> Batching:
        """This batching with "auto" resolved for `backend` (default: `jax.default_backend()`, read when a step is
        traced)."""
        backend = jax.default_backend() if backend is None else backend
        mode = ("chunked" if backend in CHUNKED_BACKENDS else "whole") if self.mode == "auto" else self.mode
        loops = self.solver_loops
        if loops == "auto":
            loops = "looped" if backend in LOOPED_SOLVER_BACKENDS else "unrolled"
        return Batching(mode, self.chunk_limit, loops)

    @property
    def chunked(self) -> bool:
        """Chunked with the batch-last layout (a resolved batching)."""
        return self.mode == "chunked"


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


def vmap_in_chunks(function, chunk_limit: int = BATCH_CHUNK):
    """`function` with a vmap rule that runs batches larger than `chunk_limit` as a loop over equal chunks.

    Each chunk is an ordinary `jax.vmap` of `function`; the last scene is repeated to fill the last chunk.
    """
    wrapped = jax.custom_batching.custom_vmap(function)

    @wrapped.def_vmap
    def rule(axis_size, in_batched, *args):
        num_chunks = -(-axis_size // chunk_limit)
        chunk = -(-axis_size // num_chunks)
        padded = num_chunks * chunk
        leaves, tree = jax.tree_util.tree_flatten(args)
        batched = jax.tree_util.tree_leaves(tuple(in_batched))
        axes = jax.tree_util.tree_unflatten(tree, [0 if b else None for b in batched])
        if num_chunks == 1:
            out = jax.vmap(function, in_axes=axes)(*args)
            return out, jax.tree_util.tree_map(lambda _: True, out)

        def split(x):
            """(B, ...) -> (chunks, chunk, ...), padded by repeating the last scene."""
            if padded > axis_size:
                x = jnp.concatenate([x, jnp.repeat(x[-1:], padded - axis_size, axis=0)])
            return x.reshape((num_chunks, chunk) + x.shape[1:])

        def call(chunk_leaves):
            chunk_leaves = iter(chunk_leaves)
            full = [next(chunk_leaves) if b else x for x, b in zip(leaves, batched, strict=True)]
            return jax.vmap(function, in_axes=axes)(*jax.tree_util.tree_unflatten(tree, full))

        out = jax.lax.map(call, [split(jnp.asarray(x)) for x, b in zip(leaves, batched, strict=True) if b])
        out = jax.tree_util.tree_map(lambda x: x.reshape((padded,) + x.shape[2:])[:axis_size], out)
        return out, jax.tree_util.tree_map(lambda _: True, out)

    return wrapped
