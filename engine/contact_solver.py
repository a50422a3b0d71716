"""Contact constraints: prepared once per step from the manifolds, then solved colour by colour each substep.

Each pair has four rows: the normal rows of its two points, then their friction rows, solved in that order.
Pairs of one colour share no movable body and are solved at once; colours are swept in order (Gauss-Seidel).

Preparation works on one scene. The solve functions are rank-polymorphic: per-scene axes first, any number of
trailing batch axes (see `engine.batch_last`), with body velocities and poses shaped (N+1, 3, *batch).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from engine.collision import Manifolds
from engine.geometry import dot2
from engine.pairs import PairLayout
from engine.softness import Softness

NUM_ROWS = 4
"""Rows per pair: normal point 0, normal point 1, friction point 0, friction point 1."""


@struct.dataclass
class ContactGeometry:
    """Compact per-point contact data of one step in colour layout (C colours, W pairs, 2 points).

    This is what crosses into the solver; `build_rows` expands it into constraint rows there.
    """

    normal: jnp.ndarray  # (C, W, 2) unit, from body a to body b
    lever_a: jnp.ndarray  # (C, W, 2, 2) [m] point minus a's centre, per point
    lever_b: jnp.ndarray  # (C, W, 2, 2) [m]
    separation: jnp.ndarray  # (C, W, 2) [m] of each point at the start of the step
    approach_velocity: jnp.ndarray  # (C, W, 2) [m/s] normal relative velocity at impact
    friction: jnp.ndarray  # (C, W, 1) [-] mixed coefficient
    restitution: jnp.ndarray  # (C, W, 1) [-] mixed coefficient
    enabled: jnp.ndarray  # (C, W, 2) bool, per point
    softness: Softness  # fields (C, W, 1): stiffer against static bodies


@struct.dataclass
class ContactRows:
    """Per-row constants of the contact constraints in colour layout (C colours, W pairs, 4 rows).

    Body indices of each slot are static: `PairLayout.colour_body_a` / `colour_body_b`.
    """

    jacobian_a: jnp.ndarray  # (C, W, 4, 3) d(row velocity)/d(vx, vy, w) of body a
    jacobian_b: jnp.ndarray  # (C, W, 4, 3)
    response_a: jnp.ndarray  # (C, W, 4, 3) velocity change of body a per unit row impulse
    response_b: jnp.ndarray  # (C, W, 4, 3)
    mass: jnp.ndarray  # (C, W, 4) [kg] effective mass of each row (0 when disabled)
    coupling: jnp.ndarray  # (C, W, 4, 4) speed change of row r per unit impulse on row s (Delassus matrix)
    geometry: ContactGeometry  # what the rows were built from


@struct.dataclass
class ContactImpulses:
    """Accumulated per-substep impulses in colour layout."""

    impulse: jnp.ndarray  # (C, W, 4) [N s] normal 0, normal 1, tangent 0, tangent 1
    max_normal: jnp.ndarray  # (C, W, 2) [N s] largest normal impulse of the step (restitution needs contact)


def prepare_contacts(
    manifolds: Manifolds,
    pair_enabled,
    *,
    pair_static,
    centre,
    velocity,
    acceleration,
    friction,
    restitution,
    layout: PairLayout,
    softness: Softness,
    static_softness: Softness,
) -> ContactGeometry:
    """Contact geometry of every candidate pair, gathered into colour layout.

    `centre` (N, 2), `velocity` (N, 3) and `acceleration` (N, 3) describe the bodies at the start of the step.
    The approach velocity that restitution reverses is the speed at impact: points still apart at the start of
    the step close the remaining gap under the step's accelerations before they touch.
    """
    a, b = layout.body_a, layout.body_b
    lever_a = manifolds.point - centre[a][:, None, :]
    lever_b = manifolds.point - centre[b][:, None, :]
    enabled = manifolds.valid & pair_enabled[:, None]

    def normal_rate(per_body):
        def point_rate(index, lever):
            rate = per_body[index][:, None, :]
            return rate[..., :2] + rate[..., 2:] * jnp.stack([-lever[..., 1], lever[..., 0]], -1)

        relative = point_rate(b, lever_b) - point_rate(a, lever_a)
        return dot2(relative, manifolds.normal[:, None, :])

    start_speed, closing_acceleration = normal_rate(velocity), normal_rate(acceleration)
    gap = jnp.maximum(manifolds.separation, 0.0)
    impact_speed = -jnp.sqrt(jnp.maximum(start_speed**2 - 2.0 * closing_acceleration * gap, 0.0))
    approach = jnp.where(start_speed < 0, impact_speed, start_speed)
    soft = jax.tree_util.tree_map(lambda s, h: jnp.where(pair_static, h, s)[:, None], softness, static_softness)
    per_pair = ContactGeometry(
        normal=manifolds.normal,
        lever_a=lever_a,
        lever_b=lever_b,
        separation=jnp.where(enabled, manifolds.separation, 0.0),
        approach_velocity=jnp.where(enabled, approach, 0.0),
        friction=friction[:, None],
        restitution=restitution[:, None],
        enabled=enabled,
        softness=soft,
    )
    return to_colour_layout(per_pair, layout)


def build_rows(geometry: ContactGeometry, response_scale, layout: PairLayout) -> ContactRows:
    """Constraint rows from contact geometry (rank-polymorphic; `response_scale` is (N+1, 3, *batch))."""
    g = geometry
    scale_a = response_scale[layout.colour_body_a]
    scale_b = response_scale[layout.colour_body_b]
    nx, ny = g.normal[:, :, 0], g.normal[:, :, 1]
    directions = ((nx, ny), (nx, ny), (-ny, nx), (-ny, nx))
    jac_a, jac_b = [], []
    for r, (dx, dy) in enumerate(directions):
        point = r % 2
        on = g.enabled[:, :, point][:, :, None]
        la, lb = g.lever_a[:, :, point], g.lever_b[:, :, point]
        ja = jnp.stack([-dx, -dy, la[:, :, 1] * dx - la[:, :, 0] * dy], 2)
        jb = jnp.stack([dx, dy, lb[:, :, 0] * dy - lb[:, :, 1] * dx], 2)
        jac_a.append(jnp.where(on, ja, 0.0))
        jac_b.append(jnp.where(on, jb, 0.0))
    jac_a, jac_b = jnp.stack(jac_a, 2), jnp.stack(jac_b, 2)
    resp_a, resp_b = scale_a[:, :, None] * jac_a, scale_b[:, :, None] * jac_b
    # Explicit component sums (not a reduction): the same rounding whether or not a batch axis trails.
    rows_a, cols_a = jac_a[:, :, :, None], resp_a[:, :, None]
    rows_b, cols_b = jac_b[:, :, :, None], resp_b[:, :, None]
    coupling = sum(
        rows_a[:, :, :, :, c] * cols_a[:, :, :, :, c] + rows_b[:, :, :, :, c] * cols_b[:, :, :, :, c] for c in range(3)
    )
    k = jnp.stack([coupling[:, :, r, r] for r in range(NUM_ROWS)], 2)
    mass = jnp.where(k > 0, 1.0 / jnp.where(k > 0, k, 1.0), 0.0)
    return ContactRows(
        jacobian_a=jac_a,
        jacobian_b=jac_b,
        response_a=resp_a,
        response_b=resp_b,
        mass=mass,
        coupling=coupling,
        geometry=g,
    )


def to_colour_layout(per_pair, layout: PairLayout):
    """Gather (K, ...) pair arrays into (C, W, ...) colour layout; padding slots are zero."""

    def gather(x):
        padded = jnp.concatenate([x, jnp.zeros((1,) + x.shape[1:], x.dtype)])
        return padded[layout.colour_slots]

    return jax.tree_util.tree_map(gather, per_pair)


def from_colour_layout(coloured, layout: PairLayout):
    """Inverse of `to_colour_layout`: (C, W, ...) back to (K, ...)."""
    order = np.argsort(layout.colour_slots.reshape(-1), kind="stable")[: layout.num_pairs]
    return jax.tree_util.tree_map(lambda x: x.reshape((-1,) + x.shape[2:])[order], coloured)


def _row_speed(rows: ContactRows, r: int, vel_a, vel_b):
    """Velocity along row `r` of each pair: (W, *batch); body velocities (W, 3, *batch)."""
    ja, jb = rows.jacobian_a[:, r], rows.jacobian_b[:, r]
    return (
        ja[:, 0] * vel_a[:, 0]
        + ja[:, 1] * vel_a[:, 1]
        + ja[:, 2] * vel_a[:, 2]
        + jb[:, 0] * vel_b[:, 0]
        + jb[:, 1] * vel_b[:, 1]
        + jb[:, 2] * vel_b[:, 2]
    )


def _apply_rows(rows: ContactRows, vel_a, vel_b, deltas):
    """Body velocities (W, 3, *batch) after impulse `deltas[r]` (W, *batch) along each row r."""
    for r, delta in enumerate(deltas):
        vel_a = vel_a + rows.response_a[:, r] * delta[:, None]
        vel_b = vel_b + rows.response_b[:, r] * delta[:, None]
    return vel_a, vel_b


def _speed_after(rows: ContactRows, r: int, speed, deltas):
    """Speed along row r after the impulse changes `deltas` of the rows solved before it."""
    for s, delta in enumerate(deltas):
        speed = speed + rows.coupling[:, r, s] * delta
    return speed


def warm_start_contacts(velocity, rows: ContactRows, impulses: ContactImpulses, layout: PairLayout):
    """Apply the accumulated impulses of every row to the (N+1, 3, *batch) velocities at once."""
    impulse = impulses.impulse
    delta_a = sum(rows.response_a[:, :, r] * impulse[:, :, r, None] for r in range(NUM_ROWS))
    delta_b = sum(rows.response_b[:, :, r] * impulse[:, :, r, None] for r in range(NUM_ROWS))
    flat = (-1,) + delta_a.shape[2:]
    velocity = velocity.at[layout.colour_body_a.reshape(-1)].add(delta_a.reshape(flat))
    return velocity.at[layout.colour_body_b.reshape(-1)].add(delta_b.reshape(flat))


def _sweep(velocity, rows: ContactRows, impulse, layout: PairLayout, solve_colour):
    """Visit the colours in order (Gauss-Seidel across colours), all pairs of a colour at once.

    `solve_colour(c, rows, impulse, vel_a, vel_b) -> (W, 4, *batch)` is the new impulses of colour `c` from its
    impulses `impulse` (W, 4, *batch) and the velocities of its bodies. They are written to the (C, W, 4, *batch)
    impulses before the velocities are updated from there, so that the compiler computes them once instead of
    again inside every velocity update. Colours are unrolled: static slices and static body indices are several
    times faster on CPU than a `lax.scan`.
    """
    for c in range(layout.num_colours):
        a, b = layout.colour_body_a[c], layout.colour_body_b[c]
        colour_rows, vel_a, vel_b = _colour(rows, c), velocity[a], velocity[b]
        old = impulse[c]
        impulse = impulse.at[c].set(solve_colour(c, colour_rows, old, vel_a, vel_b))
        new = impulse[c]
        vel_a, vel_b = _apply_rows(colour_rows, vel_a, vel_b, [new[:, r] - old[:, r] for r in range(NUM_ROWS)])
        velocity = velocity.at[a].set(vel_a).at[b].set(vel_b)
    return velocity, impulse


def _colour(tree, c: int):
    return jax.tree_util.tree_map(lambda x: x[c], tree)


def solve_contacts(
    velocity,
    moved,
    rows: ContactRows,
    impulses: ContactImpulses,
    layout: PairLayout,
    inverse_substep,
    max_push_velocity,
    use_bias,
):
    """One sweep of normal rows, then friction rows, of every pair; returns velocities and impulses.

    `moved` (N+1, 3, *batch) is each body's displacement since the start of the step; `use_bias` selects the
    soft position-correcting solve, otherwise the relaxing solve without position bias.
    """

    def solve_colour(c, rows, impulse, vel_a, vel_b):
        g = rows.geometry
        moved_a, moved_b = moved[layout.colour_body_a[c]], moved[layout.colour_body_b[c]]
        deltas, new_impulses = [], []
        for p in range(2):
            separation = g.separation[:, p] + _row_speed(rows, p, moved_a, moved_b)
            speculative = separation > 0
            pushing = use_bias & ~speculative
            bias = jnp.where(
                speculative,
                separation * inverse_substep,
                jnp.where(use_bias, jnp.maximum(g.softness.bias_rate[:, 0] * separation, -max_push_velocity), 0.0),
            )
            mass_scale = jnp.where(pushing, g.softness.mass_scale[:, 0], 1.0)
            impulse_scale = jnp.where(pushing, g.softness.impulse_scale[:, 0], 0.0)
            speed = _speed_after(rows, p, _row_speed(rows, p, vel_a, vel_b), deltas)
            old = impulse[:, p]
            new = old - rows.mass[:, p] * mass_scale * (speed + bias) - impulse_scale * old
            new = jnp.where(g.enabled[:, p], jnp.maximum(new, 0.0), 0.0)
            deltas.append(new - old)
            new_impulses.append(new)
        for p in range(2):
            r = 2 + p
            speed = _speed_after(rows, r, _row_speed(rows, r, vel_a, vel_b), deltas)
            old = impulse[:, r]
            bound = g.friction[:, 0] * new_impulses[p]
            new = jnp.clip(old - rows.mass[:, r] * speed, -bound, bound)
            deltas.append(new - old)
            new_impulses.append(new)
        return jnp.stack(new_impulses, 1)

    velocity, impulse = _sweep(velocity, rows, impulses.impulse, layout, solve_colour)
    return velocity, ContactImpulses(impulse, jnp.maximum(impulses.max_normal, impulse[:, :, :2]))


def apply_restitution(velocity, rows: ContactRows, impulses: ContactImpulses, layout: PairLayout, threshold):
    """Bounce: drive the normal velocity of points that approached faster than `threshold` to -e times that speed."""

    def solve_colour(c, rows, impulse, vel_a, vel_b):
        g = rows.geometry
        deltas, normal = [], []
        for p in range(2):
            approach = g.approach_velocity[:, p]
            applies = (
                g.enabled[:, p]
                & (g.restitution[:, 0] > 0)
                & (approach < -threshold)
                & (impulses.max_normal[c][:, p] > 0)
            )
            old = impulse[:, p]
            speed = _speed_after(rows, p, _row_speed(rows, p, vel_a, vel_b), deltas)
            new = jnp.where(
                applies, jnp.maximum(old - rows.mass[:, p] * (speed + g.restitution[:, 0] * approach), 0.0), old
            )
            deltas.append(new - old)
            normal.append(new)
        return jnp.stack(normal + [impulse[:, 2], impulse[:, 3]], 1)

    velocity, impulse = _sweep(velocity, rows, impulses.impulse, layout, solve_colour)
    return velocity, impulses.replace(impulse=impulse)
