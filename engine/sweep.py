"""Gauss-Seidel sweeps (colours of contacts, joints): as one software-pipelined `lax.scan`, or unrolled.

A sweep visits items in order; each item's new impulses depend on the velocities left by the items before it.
Written naively, XLA fuses the computation of an item's new impulses into every consumer (each velocity
component it updates, or the write into the sweep's result) and computes it several times over; on CPU,
`optimization_barrier` does not prevent this (the CPU pipeline removes barriers before fusion). Values carried
across a loop iteration are always materialised, so the sweep is pipelined: step i writes item i-1's new impulses
into the carried result and applies their change to the velocities, then solves item i and carries its new
impulses to step i+1; the last item is written and applied after the loop. Item i's solve reads its impulses at
the sweep's start from the carried result (where they are still unchanged), so the write of step i comes before
the carried value is replaced and XLA keeps both in place, with no copy per step. The body is compiled once
whatever the number of items. A single item is solved in a loop of two steps, the second doing nothing (under a
`cond`), and applied after it.

`unrolled_sweep` does the same arithmetic with each item's code written out in order: no loop step per item, and
the compiler may fuse across items, so a step runs far fewer kernels (what an accelerator pays for), at the price
of a compiled size that grows with the number of items and, on CPU, of solves recomputed inside every fused
consumer. `SWEEPS` names both; `engine.StaticSimParams.batching` picks one ("auto": per backend).
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp

Motion = tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray]
"""Per-body x, y and angular components (velocities [m/s, m/s, rad/s] or poses [m, m, rad]), each (N+1, *batch)."""


Sweep = Callable
"""`sweep(velocity, count, old, gather, solve, apply) -> (velocity, new impulses)`, as `pipelined_sweep`."""


def pipelined_sweep(velocity, count: int, old, gather, solve, apply):
    """Solve `count` items in order; returns the velocities and the new impulses (leading item axis).

    `old` holds every item's impulses at the start of the sweep (pytree, leading item axis).
    `gather(velocity, i) -> inputs` reads what item i needs from the current velocities, and
    `solve(inputs, i, start) -> new` gives its new impulses from its impulses `start` at the sweep's start
    (pytrees of one item); the inputs are materialised between the two, so that each output of `solve` does not
    read them again from the velocities.
    `apply(velocity, i, change) -> velocity` applies a change `change` of item i's impulses.
    """
    if count == 0:
        return velocity, old
    leaves, treedef = jax.tree_util.tree_flatten(old)

    def take(buffer, i):
        return jax.tree_util.tree_unflatten(treedef, [x[i] for x in buffer])

    def change_from(new, i):
        return jax.tree_util.tree_map(lambda n, o: n - o, new, take(leaves, i))

    if count == 1:
        return _single_item_sweep(velocity, take(leaves, 0), gather, solve, apply)

    def put(buffer, i, values):
        values = jax.tree_util.tree_leaves(values)
        return tuple(jax.lax.dynamic_update_index_in_dim(x, y, i, 0) for x, y in zip(buffer, values, strict=True))

    def step(carry, i):
        velocity, impulses, previous = carry
        before = jnp.maximum(i - 1, 0)
        impulses = put(impulses, before, previous)
        velocity = apply(velocity, before, change_from(previous, before))  # step 0: a zero change
        return (velocity, impulses, solve(gather(velocity, i), i, take(impulses, i))), None

    (velocity, impulses, last), _ = jax.lax.scan(step, (velocity, tuple(leaves), take(leaves, 0)), jnp.arange(count))
    impulses = put(impulses, count - 1, last)
    velocity = apply(velocity, count - 1, change_from(last, count - 1))
    return velocity, jax.tree_util.tree_unflatten(treedef, list(impulses))


def _single_item_sweep(velocity, start, gather, solve, apply):
    """One item as a loop of two steps, the second doing nothing, so that XLA keeps the loop (it inlines a loop of
    one step) and its new impulses are materialised before they are applied."""

    def step(new, i):
        return jax.lax.cond(i == 0, lambda: solve(gather(velocity, 0), 0, start), lambda: new), None

    new, _ = jax.lax.scan(step, start, jnp.arange(2))
    change = jax.tree_util.tree_map(lambda n, o: n - o, new, start)
    return apply(velocity, 0, change), jax.tree_util.tree_map(lambda x: x[None], new)


def unrolled_sweep(velocity, count: int, old, gather, solve, apply):
    """`pipelined_sweep`'s result, with the items' solves and applications written out one after another."""
    if count == 0:
        return velocity, old
    leaves, treedef = jax.tree_util.tree_flatten(old)
    new_items = []
    for i in range(count):
        start = jax.tree_util.tree_unflatten(treedef, [x[i] for x in leaves])
        new = solve(gather(velocity, i), i, start)
        velocity = apply(velocity, i, jax.tree_util.tree_map(jnp.subtract, new, start))
        new_items.append(new)
    return velocity, jax.tree_util.tree_map(lambda *items: jnp.stack(items), *new_items)


SWEEPS: dict[str, Sweep] = {"looped": pipelined_sweep, "unrolled": unrolled_sweep}
"""Sweep forms by name: "looped" compiles one loop body whatever the number of items; "unrolled" writes every item
out (fewer kernels per step, larger programs)."""
