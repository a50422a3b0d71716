"""Gauss-Seidel sweeps (colours of contacts, joints) as one software-pipelined `lax.scan`.

A sweep visits items in order; each item's new impulses depend on the velocities left by the items before it.
Written naively, XLA fuses the computation of an item's new impulses into every consumer (each velocity
component it updates) and computes it several times over; on CPU, `optimization_barrier` does not prevent this.
Values carried across a loop iteration are always materialised, so the sweep is pipelined: step i applies item
i-1's impulse changes to the velocities, then solves item i and carries its new impulses to step i+1; the last
item's change is applied after the loop. The body is compiled once whatever the number of items. XLA inlines a
loop of one step, so a single item runs as two steps, the second only applying (under a `cond`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

Motion = tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray]
"""Per-body x, y and angular components (velocities [m/s, m/s, rad/s] or poses [m, m, rad]), each (N+1, *batch)."""


def pipelined_sweep(velocity, count: int, old, gather, solve, apply):
    """Solve `count` items in order; returns the velocities and the new impulses (leading item axis).

    `old` holds every item's impulses at the start of the sweep (pytree, leading item axis).
    `gather(velocity, i) -> inputs` reads what item i needs from the current velocities, and
    `solve(inputs, i) -> new` gives its new impulses (pytree of one item); the inputs are materialised between
    the two, so that each output of `solve` does not read them again from the velocities.
    `apply(velocity, i, change) -> velocity` applies a change `change` of item i's impulses.
    """
    if count == 0:
        return velocity, old

    def take(tree, i):
        return jax.tree_util.tree_map(lambda x: x[i], tree)

    steps = max(count, 2)

    def step(carry, i):
        velocity, previous = carry
        before = jnp.maximum(i - 1, 0)
        change = jax.tree_util.tree_map(lambda n, o: n - o, previous, take(old, before))
        velocity = apply(velocity, before, change)  # step 0 applies a zero change (item 0's start impulses)
        inputs = gather(velocity, jnp.minimum(i, count - 1))
        if steps == count:
            new = solve(inputs, i)
        else:
            new = jax.lax.cond(i < count, lambda: solve(inputs, i), lambda: previous)
        return (velocity, new), previous

    (velocity, last), emitted = jax.lax.scan(step, (velocity, take(old, 0)), jnp.arange(steps))
    if steps > count:
        return velocity, jax.tree_util.tree_map(lambda x: x[1:], emitted)
    change = jax.tree_util.tree_map(lambda n, o: n - o, last, take(old, count - 1))
    new = jax.tree_util.tree_map(lambda x, y: jnp.concatenate([x[1:], y[None]]), emitted, last)
    return apply(velocity, count - 1, change), new
