"""Contact constraints: prepared once per step from the manifolds, then solved colour by colour each substep.

Each pair has four rows: the normal rows of its two points, then their friction rows, solved in that order.
Pairs of one colour share no movable body and are solved at once; colours are swept in order (Gauss-Seidel) by
one of `engine.sweep.SWEEPS` (looped, its body compiled once however many colours there are, or unrolled).

Preparation works on one scene. The solve functions are rank-polymorphic: per-scene axes first, any number of
trailing batch axes (see `engine.batch_last`). They work on structures of arrays, which XLA compiles to plain
element-wise loops: body velocities and poses are `Motion` triples of (N+1, *batch) arrays, and every row
quantity is its own (C, W, *batch) array.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from kforge.engine.collision import Manifolds
from kforge.engine.geometry import dot2
from kforge.engine.pairs import PairLayout
from kforge.engine.softness import Softness
from kforge.engine.sweep import Motion, Sweep

NUM_ROWS = 4
"""Rows per pair: normal point 0, normal point 1, friction point 0, friction point 1."""

NUM_POINTS = 2
"""Contact points per pair; row r acts at point r % 2."""


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
    batch: jnp.ndarray  # (C, W) i32 the Jax2D solver batch of each pair (`engine.jax2d_contacts`), else 0


@struct.dataclass
class PushLaw:
    """Per-scene constants of Baumgarte's push-out (`engine.params.ContactLaw.BAUMGARTE`)."""

    depth: jnp.ndarray  # [m] under the soft law, points deeper than this at the step's start follow BAUMGARTE's
    rate: jnp.ndarray  # [1/s] normal speed per metre of overlap beyond the slop
    slop: jnp.ndarray  # [m]


@struct.dataclass
class ContactImpulses:
    """Accumulated per-substep impulses in colour layout, one (C, W, *batch) array per row."""

    impulse: tuple  # (4,) of arrays [N s]: normal 0, normal 1, tangent 0, tangent 1
    max_normal: tuple  # (2,) of arrays [N s] largest normal impulse of the step (restitution needs contact)


@struct.dataclass
class PairConstants:
    """Per candidate pair (K,) constants of one step."""

    enabled: jnp.ndarray  # (K,) bool: both active, not both static, their collision modes and matrix allow contact
    friction: jnp.ndarray  # (K,) [-] mixed coefficient
    restitution: jnp.ndarray  # (K,) [-] mixed coefficient
    softness: Softness  # fields (K,): stiffer against static bodies


def prepare_contacts(
    manifolds: Manifolds, pairs: PairConstants, centre, velocity, acceleration, layout: PairLayout
) -> ContactGeometry:
    """Contact geometry of every candidate pair, gathered into colour layout.

    `centre` (N, 2), `velocity` (N, 3) and `acceleration` (N, 3) describe the bodies at the start of the step.
    The approach velocity that restitution reverses is the speed at impact: points still apart at the start of
    the step close the remaining gap under the step's accelerations before they touch.
    """
    a, b = layout.body_a, layout.body_b
    lever_a = manifolds.point - centre[a][:, None, :]
    lever_b = manifolds.point - centre[b][:, None, :]
    enabled = manifolds.valid & pairs.enabled[:, None]

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
    per_pair = ContactGeometry(
        normal=manifolds.normal,
        lever_a=lever_a,
        lever_b=lever_b,
        separation=jnp.where(enabled, manifolds.separation, 0.0),
        approach_velocity=jnp.where(enabled, approach, 0.0),
        friction=pairs.friction[:, None],
        restitution=pairs.restitution[:, None],
        enabled=enabled,
        softness=jax.tree_util.tree_map(lambda x: x[:, None], pairs.softness),
        batch=jnp.zeros(layout.num_pairs, jnp.int32),
    )
    return to_colour_layout(per_pair, layout)


@struct.dataclass
class ContactRows:
    """Per-row constants of the contact constraints in colour layout: every field is (C, W, *batch) or a tuple of such.

    Row r pushes along d_r, the normal (n_x, n_y) for r = 0, 1 and the tangent (-n_y, n_x) for r = 2, 3, at point
    r % 2. Its speed is (v_b - v_a) . d_r + w_b * arm_b[r] - w_a * arm_a[r]. Body indices of each slot are static:
    `PairLayout.colour_body_a` / `colour_body_b`.
    """

    normal_x: jnp.ndarray  # unit normal from body a to body b
    normal_y: jnp.ndarray
    arm_a: tuple  # (4,) of arrays [m] lever of the row's point about a's centre, crossed with d_r (0 if disabled)
    arm_b: tuple  # (4,) of arrays [m]
    inverse_mass_a: jnp.ndarray  # [1/kg] 0 if a cannot move
    inverse_inertia_a: jnp.ndarray  # [1/(kg m^2)]
    inverse_mass_b: jnp.ndarray
    inverse_inertia_b: jnp.ndarray
    mass: tuple  # (4,) of arrays [kg] effective mass of each row (0 when its point is disabled)
    coupling: tuple  # (6,) of arrays: speed change of row r per unit impulse on row s < r, see `_coupling`
    separation: tuple  # (2,) of arrays [m] of each point at the start of the step
    approach_velocity: tuple  # (2,) of arrays [m/s] normal relative velocity at impact
    enabled: tuple  # (2,) of bool arrays, per point
    friction: jnp.ndarray  # [-] mixed coefficient
    restitution: jnp.ndarray  # [-] mixed coefficient
    softness: Softness  # fields (C, W, *batch): stiffer against static bodies


def _direction(rows: ContactRows, r: int):
    """Direction d_r of row r: the normal for the normal rows, the tangent (-n_y, n_x) for the friction rows."""
    if r < NUM_POINTS:
        return rows.normal_x, rows.normal_y
    return -rows.normal_y, rows.normal_x


def _coupling_index(r: int, s: int) -> int:
    """Position of the (r, s) entry, s < r, in `ContactRows.coupling`."""
    return r * (r - 1) // 2 + s


def build_rows(geometry: ContactGeometry, response_scale, layout: PairLayout) -> ContactRows:
    """Constraint rows from contact geometry (rank-polymorphic; `response_scale` is (N+1, 3, *batch))."""
    g = geometry
    scale_a = response_scale[layout.colour_body_a]
    scale_b = response_scale[layout.colour_body_b]
    inverse_mass_a, inverse_inertia_a = scale_a[:, :, 0], scale_a[:, :, 2]
    inverse_mass_b, inverse_inertia_b = scale_b[:, :, 0], scale_b[:, :, 2]
    normal_x, normal_y = g.normal[:, :, 0], g.normal[:, :, 1]
    enabled = tuple(g.enabled[:, :, p] for p in range(NUM_POINTS))
    partial = ContactRows(
        normal_x=normal_x,
        normal_y=normal_y,
        arm_a=(),
        arm_b=(),
        inverse_mass_a=inverse_mass_a,
        inverse_inertia_a=inverse_inertia_a,
        inverse_mass_b=inverse_mass_b,
        inverse_inertia_b=inverse_inertia_b,
        mass=(),
        coupling=(),
        separation=tuple(g.separation[:, :, p] for p in range(NUM_POINTS)),
        approach_velocity=tuple(g.approach_velocity[:, :, p] for p in range(NUM_POINTS)),
        enabled=enabled,
        friction=g.friction[:, :, 0],
        restitution=g.restitution[:, :, 0],
        softness=jax.tree_util.tree_map(lambda x: x[:, :, 0], g.softness),
    )
    arm_a, arm_b = [], []
    for r in range(NUM_ROWS):
        dx, dy = _direction(partial, r)
        point = r % NUM_POINTS
        la, lb = g.lever_a[:, :, point], g.lever_b[:, :, point]
        arm_a.append(jnp.where(enabled[point], la[:, :, 0] * dy - la[:, :, 1] * dx, 0.0))
        arm_b.append(jnp.where(enabled[point], lb[:, :, 0] * dy - lb[:, :, 1] * dx, 0.0))

    def coupling(r, s):
        """J_r M^-1 J_s^T of rows r and s."""
        (rx, ry), (sx, sy) = _direction(partial, r), _direction(partial, s)
        along = rx * sx + ry * sy
        return (
            inverse_mass_a * along
            + inverse_inertia_a * arm_a[r] * arm_a[s]
            + inverse_mass_b * along
            + inverse_inertia_b * arm_b[r] * arm_b[s]
        )

    mass = []
    for r in range(NUM_ROWS):
        k = coupling(r, r)
        usable = enabled[r % NUM_POINTS] & (k > 0)
        mass.append(jnp.where(usable, 1.0 / jnp.where(usable, k, 1.0), 0.0))
    off_diagonal = [coupling(r, s) for r in range(NUM_ROWS) for s in range(r)]
    return partial.replace(arm_a=tuple(arm_a), arm_b=tuple(arm_b), mass=tuple(mass), coupling=tuple(off_diagonal))


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


def _row_speed(rows: ContactRows, r: int, motion_a: Motion, motion_b: Motion):
    """Relative velocity (or displacement) of the pair along row `r`, from the motions of its two bodies."""
    dx, dy = _direction(rows, r)
    return (
        (motion_b[0] - motion_a[0]) * dx
        + (motion_b[1] - motion_a[1]) * dy
        + motion_b[2] * rows.arm_b[r]
        - motion_a[2] * rows.arm_a[r]
    )


def _speed_after(rows: ContactRows, r: int, speed, deltas):
    """Speed along row r after the impulse changes `deltas` of the rows solved before it."""
    for s, delta in enumerate(deltas):
        speed = speed + rows.coupling[_coupling_index(r, s)] * delta
    return speed


def _velocity_changes(rows: ContactRows, deltas) -> tuple[Motion, Motion]:
    """Velocity changes of bodies a and b from impulse changes `deltas` on rows 0, 1, ... of each pair."""
    linear_x, linear_y, turn_a, turn_b = 0.0, 0.0, 0.0, 0.0
    for r, delta in enumerate(deltas):
        dx, dy = _direction(rows, r)
        linear_x = linear_x + dx * delta
        linear_y = linear_y + dy * delta
        turn_a = turn_a + rows.arm_a[r] * delta
        turn_b = turn_b + rows.arm_b[r] * delta
    change_a = (-rows.inverse_mass_a * linear_x, -rows.inverse_mass_a * linear_y, -rows.inverse_inertia_a * turn_a)
    change_b = (rows.inverse_mass_b * linear_x, rows.inverse_mass_b * linear_y, rows.inverse_inertia_b * turn_b)
    return change_a, change_b


def received_changes(layout: PairLayout) -> tuple[np.ndarray, np.ndarray]:
    """Which velocity changes each real body receives when every slot's pair acts at once: (N, D) indices into the
    flat list [changes of every slot's body a; changes of every slot's body b], in that list's order, and (N, D)
    whether each index is a real entry (D: the most any body receives; padding slots go to the dummy body N)."""
    owners = np.concatenate([layout.colour_body_a.reshape(-1), layout.colour_body_b.reshape(-1)])
    return changes_by_body(owners, layout.num_bodies)


def changes_by_body(owners: np.ndarray, num_bodies: int) -> tuple[np.ndarray, np.ndarray]:
    """For a flat list of changes whose bodies are `owners`: (N, D) the indices of each body's changes in list order,
    and (N, D) whether each index is a real entry (D: the most any body receives)."""
    entries = [np.flatnonzero(owners == body) for body in range(num_bodies)]
    width = max((len(e) for e in entries), default=0)
    indices = np.zeros((num_bodies, width), np.int32)
    real = np.zeros((num_bodies, width), bool)
    for body, found in enumerate(entries):
        indices[body, : len(found)], real[body, : len(found)] = found, True
    return indices, real


def warm_start_contacts(velocity: Motion, rows: ContactRows, impulses: ContactImpulses, layout: PairLayout) -> Motion:
    """Apply the accumulated impulses of every row to the velocities at once.

    Each body sums the changes it receives one by one in a fixed order (`received_changes`), so the result is the
    same bits on every backend; a scatter-add, where several slots change one body, is lowered to atomic additions
    of varying order on a GPU.
    """
    change_a, change_b = _velocity_changes(rows, impulses.impulse)
    indices, real = received_changes(layout)

    def received(v, da, db):
        changes = jnp.concatenate([da.reshape((-1,) + da.shape[2:]), db.reshape((-1,) + db.shape[2:])])
        return add_in_order(v, changes, indices, real)

    return tuple(received(v, da, db) for v, da, db in zip(velocity, change_a, change_b, strict=True))


def add_in_order(v, changes, indices: np.ndarray, real: np.ndarray):
    """`v` (N+1, *batch) plus, for each real body, its `changes` (M, *batch) one by one in the fixed order of
    `changes_by_body`'s `indices` and `real` (N, D): the same bits on every backend, where a scatter-add onto a body
    changed several times is lowered to atomic additions of varying order on a GPU."""
    n = indices.shape[0]
    bodies = v[:n]
    for k in range(indices.shape[1]):
        takes = real[:, k].reshape((n,) + (1,) * (v.ndim - 1))
        bodies = jnp.where(takes, bodies + changes[indices[:, k]], bodies)
    return jnp.concatenate([bodies, v[n:]])


class _ColourSolve(NamedTuple):
    """How `_sweep` solves one colour's rows: `solve(rows, impulse, vel_a, vel_b, bodies_of, extra)` returns their
    new impulses from the colour's rows, its impulses (W, *batch), the velocities of its bodies a and b, a function
    `bodies_of(motion)` giving the motions of its bodies a and b, and its slice `extra` of `per_colour` (a pytree
    with a leading colour axis, or None)."""

    solve: Callable
    per_colour: Any = None


def _sweep(velocity: Motion, rows: ContactRows, impulse, layout: PairLayout, colour_solve: _ColourSolve, sweep: Sweep):
    """Visit the colours in order (Gauss-Seidel across colours), all pairs of a colour at once, by `sweep`, solving
    each by `colour_solve`.

    `impulse` holds the (C, W, *batch) impulses of the rows to solve, rows 0, 1, ... of every pair. Returns the
    velocities and the new impulses.
    """
    solve_colour, per_colour = colour_solve
    # Per colour, the W bodies a then the W bodies b: one gather and one scatter per velocity component.
    bodies = jnp.asarray(np.concatenate([layout.colour_body_a, layout.colour_body_b], axis=1))
    width = layout.colour_body_a.shape[1]

    def colour_slice(tree, c):
        return jax.tree_util.tree_map(lambda x: x[c], tree)

    def split(motion: Motion, c) -> tuple[Motion, Motion]:
        both = tuple(m[bodies[c]] for m in motion)
        return tuple(x[:width] for x in both), tuple(x[width:] for x in both)

    def gather(velocity, _):
        # The gathers are not recomputed per output; passing the velocity whole avoids copying their slices.
        return velocity

    def solve(velocity, c, start):
        vel_a, vel_b = split(velocity, c)
        extra = colour_slice(per_colour, c)
        return solve_colour(colour_slice(rows, c), start, vel_a, vel_b, lambda motion: split(motion, c), extra)

    def apply(velocity, c, change):
        change_a, change_b = _velocity_changes(colour_slice(rows, c), change)
        return tuple(
            v.at[bodies[c]].add(jnp.concatenate([da, db]))
            for v, da, db in zip(velocity, change_a, change_b, strict=True)
        )

    return sweep(velocity, layout.num_colours, tuple(impulse), gather, solve, apply)


BLOCK_CONDITION_LIMIT = 1000.0
"""A pair's two normal rows are solved together only while k00^2 < this x det(K): nearly coincident points are
solved one after the other."""


def _block_normal_impulses(rows: ContactRows, impulse, targets):
    """Both normal impulses of each pair solved together: the 2x2 complementarity problem w = K x + b, x >= 0,
    w >= 0, x . w = 0, by trying both points pushing, then one, then none (Box2D's block solver). `targets` holds per
    point its speed plus bias at the pass's velocities and whether its row is rigid (no softness). Returns where the
    block applies (both points enabled and rigid, K well conditioned, a case found) and the new impulses."""
    (w0, rigid0), (w1, rigid1) = targets
    a0, a1 = impulse[0], impulse[1]
    usable = rows.enabled[0] & rows.enabled[1] & rigid0 & rigid1 & (rows.mass[0] > 0) & (rows.mass[1] > 0)
    k00 = 1.0 / jnp.where(usable, rows.mass[0], 1.0)
    k11 = 1.0 / jnp.where(usable, rows.mass[1], 1.0)
    k01 = rows.coupling[_coupling_index(1, 0)]
    det = k00 * k11 - k01 * k01
    usable = usable & (k00 * k00 < BLOCK_CONDITION_LIMIT * det)
    safe_det = jnp.where(usable, det, 1.0)
    b0 = w0 - k00 * a0 - k01 * a1
    b1 = w1 - k01 * a0 - k11 * a1
    both = (-(k11 * b0 - k01 * b1) / safe_det, -(k00 * b1 - k01 * b0) / safe_det)
    first = (-b0 / k00, jnp.zeros_like(b0))
    second = (jnp.zeros_like(b1), -b1 / k11)
    cases = [
        (both, (both[0] >= 0.0) & (both[1] >= 0.0)),
        (first, (first[0] >= 0.0) & (k01 * first[0] + b1 >= 0.0)),
        (second, (second[1] >= 0.0) & (k01 * second[1] + b0 >= 0.0)),
        ((jnp.zeros_like(b0), jnp.zeros_like(b1)), (b0 >= 0.0) & (b1 >= 0.0)),
    ]
    x0, x1, found = jnp.zeros_like(b0), jnp.zeros_like(b1), jnp.zeros_like(usable)
    for (c0, c1), valid in reversed(cases):
        x0, x1, found = jnp.where(valid, c0, x0), jnp.where(valid, c1, x1), found | valid
    return usable & found, (x0, x1)


@dataclasses.dataclass(frozen=True)
class ContactPass:
    """How one sweep over the contacts solves: the step's push-out settings, the laws (static) and the sweep's form."""

    inverse_substep: jnp.ndarray  # [1/s]
    max_push_velocity: jnp.ndarray  # [m/s]
    use_bias: bool | jnp.ndarray  # the soft position-correcting solve, otherwise the relaxing solve (may be traced)
    baumgarte_law: bool  # static: every point follows Baumgarte's push-out (`engine.params.ContactLaw.BAUMGARTE`)
    push_law: PushLaw
    block: bool  # static: a pair's two rigid normal rows are solved together (`_block_normal_impulses`)
    sweep: Sweep  # one of `engine.sweep.SWEEPS`


def _push_target(rows: ContactRows, p: int, separation, settings: ContactPass):
    """Bias [m/s] of normal row `p` at its current `separation`, with its mass and impulse scales (None: a rigid row,
    Baumgarte's law). Points deeper than `push_law.depth` at the step's start follow Baumgarte's push-out under the
    soft law too."""
    push_law = settings.push_law
    speculative = separation > 0
    baumgarte_bias = push_law.rate * jnp.minimum(separation + push_law.slop, 0.0)
    if settings.baumgarte_law:
        return jnp.where(speculative, separation * settings.inverse_substep, baumgarte_bias), None
    use_bias = settings.use_bias
    pushing = use_bias & ~speculative
    soft_push = jnp.maximum(rows.softness.bias_rate * separation, -settings.max_push_velocity)
    bias = jnp.where(speculative, separation * settings.inverse_substep, jnp.where(use_bias, soft_push, 0.0))
    mass_scale = jnp.where(pushing, rows.softness.mass_scale, 1.0)
    impulse_scale = jnp.where(pushing, rows.softness.impulse_scale, 0.0)
    deep = rows.separation[p] < -push_law.depth
    bias = jnp.where(deep & ~speculative, baumgarte_bias, bias)
    mass_scale = jnp.where(deep, 1.0, mass_scale)
    impulse_scale = jnp.where(deep, 0.0, impulse_scale)
    return bias, (mass_scale, impulse_scale)


def _normal_impulses(rows: ContactRows, impulse, velocities: tuple[Motion, Motion], separations, settings: ContactPass):
    """New impulses of both normal rows of every pair of a colour, one after the other (or together, with
    `settings.block`); `velocities` holds the motions of the pairs' bodies a and b."""
    deltas, new_impulses, targets = [], [], []
    for p in range(NUM_POINTS):
        bias, scales = _push_target(rows, p, separations[p], settings)
        speed = _row_speed(rows, p, *velocities)
        if settings.block:
            rigid = True if scales is None else (scales[0] == 1.0) & (scales[1] == 0.0)
            targets.append((speed + bias, rigid))
        speed = _speed_after(rows, p, speed, deltas)
        old = impulse[p]
        if scales is None:
            new = old - rows.mass[p] * (speed + bias)
        else:
            new = old - rows.mass[p] * scales[0] * (speed + bias) - scales[1] * old
        new = jnp.where(rows.enabled[p], jnp.maximum(new, 0.0), 0.0)
        deltas.append(new - old)
        new_impulses.append(new)
    if settings.block:
        solved, together = _block_normal_impulses(rows, impulse, targets)
        new_impulses = [jnp.where(solved, t, n) for t, n in zip(together, new_impulses, strict=True)]
    return new_impulses


def _friction_impulses(rows: ContactRows, impulse, velocities: tuple[Motion, Motion], normal):
    """New impulses of both friction rows of every pair of a colour, after its new normal impulses `normal`, each
    bounded by its point's normal impulse times the friction coefficient."""
    deltas = [new - old for new, old in zip(normal, impulse[:NUM_POINTS], strict=True)]
    new_impulses = []
    for p in range(NUM_POINTS):
        r = NUM_POINTS + p
        speed = _speed_after(rows, r, _row_speed(rows, r, *velocities), deltas)
        old = impulse[r]
        bound = rows.friction * normal[p]
        new = jnp.clip(old - rows.mass[r] * speed, -bound, bound)
        deltas.append(new - old)
        new_impulses.append(new)
    return new_impulses


def solve_contacts(
    velocity: Motion,
    moved: Motion | None,
    rows: ContactRows,
    impulses: ContactImpulses,
    layout: PairLayout,
    settings: ContactPass,
):
    """One sweep of normal rows, then friction rows, of every pair; returns velocities and impulses.

    `moved` is each body's displacement since the start of the step (None: every body is where it started).
    `settings.use_bias` selects the soft position-correcting solve, otherwise the relaxing solve without position
    bias. Under Baumgarte's law (every point; otherwise the points deeper than `push_law.depth` at the step's start)
    both solve the same rigid rows with `push_law`'s bias.
    """

    def solve_colour(rows, impulse, vel_a, vel_b, bodies_of, _):
        separations = rows.separation
        if moved is not None:
            moved_a, moved_b = bodies_of(moved)
            separations = tuple(rows.separation[p] + _row_speed(rows, p, moved_a, moved_b) for p in range(NUM_POINTS))
        normal = _normal_impulses(rows, impulse, (vel_a, vel_b), separations, settings)
        return tuple(normal + _friction_impulses(rows, impulse, (vel_a, vel_b), normal))

    velocity, impulse = _sweep(velocity, rows, impulses.impulse, layout, _ColourSolve(solve_colour), settings.sweep)
    max_normal = tuple(jnp.maximum(m, i) for m, i in zip(impulses.max_normal, impulse[:NUM_POINTS], strict=True))
    return velocity, ContactImpulses(impulse, max_normal)


def _bounces(rows: ContactRows, max_normal, threshold, p: int):
    """Whether point `p` of each slot bounces: enabled, elastic, pushed during the step, and approached faster than
    `threshold`."""
    approach = rows.approach_velocity[p]
    return rows.enabled[p] & (rows.restitution > 0) & (approach < -threshold) & (max_normal[p] > 0)


def bounces_anywhere(rows: ContactRows, impulses: ContactImpulses, threshold) -> jnp.ndarray:
    """Whether any point of the arrays bounces (`apply_restitution` would change it): one decision for every scene they
    hold."""
    points = [jnp.any(_bounces(rows, impulses.max_normal, threshold, p)) for p in range(NUM_POINTS)]
    return functools.reduce(jnp.logical_or, points)


def apply_restitution(
    velocity: Motion, rows: ContactRows, impulses: ContactImpulses, layout: PairLayout, threshold, sweep: Sweep
):
    """Bounce: drive the normal velocity of points that approached faster than `threshold` to -e times that speed."""

    def solve_colour(rows, impulse, vel_a, vel_b, _, max_normal):
        deltas, normal = [], []
        for p in range(NUM_POINTS):
            applies = _bounces(rows, max_normal, threshold, p)
            old = impulse[p]
            speed = _speed_after(rows, p, _row_speed(rows, p, vel_a, vel_b), deltas)
            bounce_speed = rows.restitution * rows.approach_velocity[p]
            new = jnp.where(applies, jnp.maximum(old - rows.mass[p] * (speed + bounce_speed), 0.0), old)
            deltas.append(new - old)
            normal.append(new)
        return tuple(normal)

    normal_impulses = impulses.impulse[:NUM_POINTS]
    colour_solve = _ColourSolve(solve_colour, impulses.max_normal)
    velocity, normal = _sweep(velocity, rows, normal_impulses, layout, colour_solve, sweep)
    return velocity, impulses.replace(impulse=normal + impulses.impulse[NUM_POINTS:])
