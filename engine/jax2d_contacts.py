"""Jax2D's contact order (`engine.params.ContactOrder.JAX2D`): the pairs of one kind (polygon-polygon, then
circle-polygon, then circle-circle; one colour each, in Jax2D's pair order) are solved in batches of up to
SOLVER_BATCH_SIZE pairs at once (Jacobi within a batch, batches one after another); a pair's two points are solved in
separate sweeps over the batches, each point's normal row then its friction row. A pass leaves the last pair of a
kind with no accumulated impulse when the kind's batches have padding (Jax2D's padding writes over it), so that pair
starts every pass, and every step, from zero.

Rank-polymorphic like `engine.contact_solver`: per-scene axes first, any trailing batch axes. A body's changes within a
batch are summed in a fixed order, so every backend gives the same bits."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from kforge.engine.contact_solver import (
    NUM_POINTS,
    ContactImpulses,
    ContactPass,
    ContactRows,
    _coupling_index,
    _push_target,
    _row_speed,
    _velocity_changes,
    add_in_order,
    changes_by_body,
)
from kforge.engine.pairs import PairLayout

SOLVER_BATCH_SIZE = 16
"""Pairs solved at once in one batch (Jax2D's `solver_batch_size` in Kinetix)."""


def _real_slots(layout: PairLayout) -> np.ndarray:
    """(C,) how many real pairs each colour holds."""
    return (layout.colour_slots < layout.num_pairs).sum(1)


def _num_batches(count: int) -> int:
    return -(-count // SOLVER_BATCH_SIZE)


def solver_batches(counted: jnp.ndarray, layout: PairLayout) -> jnp.ndarray:
    """(C, W) int32: the batch each slot's pair is solved in, from `counted` (K,) bool, the pairs Jax2D counts as
    touching (its manifolds' `active`). Jax2D puts the untouching pairs first, then the touching ones, each in pair
    order, and deals them out to the batches in turn."""
    padded = jnp.concatenate([counted, jnp.zeros((1,), bool)])
    rows = []
    for c, real in enumerate(_real_slots(layout)):
        batches = _num_batches(int(real))
        active = padded[layout.colour_slots[c]]
        if batches <= 1:
            rows.append(jnp.zeros(active.shape, jnp.int32))
            continue
        real_mask = np.arange(active.shape[0]) < real
        inactive = ~active & real_mask
        inactive_before = jnp.cumsum(inactive) - inactive
        active_before = jnp.cumsum(active) - active
        position = jnp.where(active, jnp.sum(inactive) + active_before, inactive_before)
        rows.append((position % batches).astype(jnp.int32))
    return jnp.stack(rows)


def _reset_slots(layout: PairLayout) -> np.ndarray:
    """(C, W) bool: the last pair of each colour whose batches have padding."""
    reset = np.zeros(layout.colour_slots.shape, bool)
    for c, real in enumerate(_real_slots(layout)):
        if real % SOLVER_BATCH_SIZE:
            reset[c, real - 1] = True
    return reset


class _Colour(NamedTuple):
    """One colour's real pairs: their rows, their bodies (every pair's body a, then every pair's body b) and which of
    those bodies' changes each body receives, in order (`changes_by_body`; the reserved static bodies, which never
    move, receive none)."""

    rows: ContactRows
    bodies: np.ndarray
    received: tuple[np.ndarray, np.ndarray]

    @classmethod
    def of(cls, rows: ContactRows, layout: PairLayout, c: int, real: int) -> _Colour:
        """Colour `c` of `rows`, its first `real` slots."""
        bodies = np.concatenate([layout.colour_body_a[c, :real], layout.colour_body_b[c, :real]])
        receivers = np.where(bodies < layout.num_reserved_static, -1, bodies)
        colour_rows = jax.tree_util.tree_map(lambda x: x[c, :real], rows)
        return cls(colour_rows, bodies, changes_by_body(receivers, layout.num_bodies))


def _solve_point(velocity, colour: _Colour, impulse, p: int, in_batch, settings: ContactPass):
    """Point `p` of every pair of `colour` in `in_batch` at once: its normal row, then its friction row."""
    rows, bodies = colour.rows, colour.bodies
    width = bodies.shape[0] // 2
    motion = tuple(v[bodies] for v in velocity)
    vel_a, vel_b = tuple(m[:width] for m in motion), tuple(m[width:] for m in motion)
    bias, _ = _push_target(rows, p, rows.separation[p], settings)
    old_normal, old_friction = impulse[p], impulse[NUM_POINTS + p]
    normal = old_normal - rows.mass[p] * (_row_speed(rows, p, vel_a, vel_b) + bias)
    normal = jnp.where(rows.enabled[p], jnp.maximum(normal, 0.0), 0.0)
    normal = jnp.where(in_batch, normal, old_normal)
    r = NUM_POINTS + p
    friction_speed = _row_speed(rows, r, vel_a, vel_b) + rows.coupling[_coupling_index(r, p)] * (normal - old_normal)
    bound = rows.friction * normal
    friction = jnp.clip(old_friction - rows.mass[r] * friction_speed, -bound, bound)
    friction = jnp.where(in_batch, friction, old_friction)
    deltas = [jnp.zeros_like(normal)] * len(impulse)
    deltas[p], deltas[r] = normal - old_normal, friction - old_friction
    change_a, change_b = _velocity_changes(rows, deltas)
    indices, real = colour.received
    velocity = tuple(
        add_in_order(v, jnp.concatenate([da, db]), indices, real)
        for v, da, db in zip(velocity, change_a, change_b, strict=True)
    )
    impulse = list(impulse)
    impulse[p], impulse[r] = normal, friction
    return velocity, impulse


def solve_contacts_jax2d(
    velocity, rows: ContactRows, impulses: ContactImpulses, layout: PairLayout, batches, settings: ContactPass
):
    """One pass over every contact in Jax2D's order (`batches`: `solver_batches`); returns velocities and impulses.
    Jax2D's contacts follow Baumgarte's law with the separations of the step's start."""
    reset = _reset_slots(layout)
    per_colour = []
    width = layout.colour_slots.shape[1]
    for c, real in enumerate(_real_slots(layout)):
        real = int(real)  # the colour's real pairs come first: only they are solved
        colour = _Colour.of(rows, layout, c, real)
        impulse = [x[c, :real] for x in impulses.impulse]
        points = NUM_POINTS if layout.colour_slots[c, 0] < layout.num_polygon_polygon else 1
        for p in range(points):
            for b in range(_num_batches(real)):
                in_batch = batches[c, :real] == b
                velocity, impulse = _solve_point(velocity, colour, impulse, p, in_batch, settings)
        if reset[c].any():
            keep = jnp.asarray(~reset[c, :real]).reshape((real,) + (1,) * (impulse[0].ndim - 1))
            impulse = [jnp.where(keep, x, 0.0) for x in impulse]
        padding = [(0, width - real)] + [(0, 0)] * (impulse[0].ndim - 1)
        per_colour.append([jnp.pad(x, padding) for x in impulse])
    impulse = tuple(jnp.stack([colour[r] for colour in per_colour]) for r in range(len(impulses.impulse)))
    max_normal = tuple(jnp.maximum(m, i) for m, i in zip(impulses.max_normal, impulse[:NUM_POINTS], strict=True))
    return velocity, ContactImpulses(impulse, max_normal)
