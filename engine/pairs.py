"""Candidate shape pairs of a static size, and their grouping into independent solver colours.

Pairs are fixed per `StaticSimParams`: every unordered pair of body slots except pairs of two reserved static
slots. They are ordered polygon-polygon, then polygon-circle (polygon first), then circle-circle. Whether a
pair can actually collide (active, not both static, collision modes, joints) is decided per scene at run time.

The contact solver is Gauss-Seidel across colours and parallel within a colour: in one colour no movable body
appears twice (reserved static slots may repeat, they never move), so the colour's pairs can be solved at once
with the same result as solving them one after another.
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np

from kforge.engine.params import ContactOrder, StaticSimParams


@dataclasses.dataclass(frozen=True, eq=False)
class PairLayout:
    """Static index arrays describing the candidate pairs of one size."""

    body_a: np.ndarray  # (K,) i32, lower global index of the pair
    body_b: np.ndarray  # (K,) i32, higher global index
    num_bodies: int  # N; colour padding uses the dummy body index N
    num_reserved_static: int  # bodies 0.. that are always static
    num_polygon_polygon: int
    num_polygon_circle: int
    num_circle_circle: int
    colour_slots: np.ndarray  # (colours, width) i32 pair index, K = padding (no pair)
    colour_body_a: np.ndarray  # (colours, width) i32 body_a of each slot, N for padding
    colour_body_b: np.ndarray  # (colours, width) i32 body_b of each slot, N for padding

    @property
    def num_pairs(self) -> int:
        return int(self.body_a.shape[0])

    @property
    def num_colours(self) -> int:
        return int(self.colour_slots.shape[0])


COLOURING_ATTEMPTS = 200
"""Random pair orders tried per (colours, width) target when searching a balanced colouring."""


def _try_colouring(
    pairs: list[tuple[int, int]], order: np.ndarray, num_reserved: int, num_colours: int, width: int
) -> list[list[int]] | None:
    """Assign pairs (in `order`) to the least-filled colour where their movable bodies are free."""
    colours: list[list[int]] = [[] for _ in range(num_colours)]
    used: list[set[int]] = [set() for _ in range(num_colours)]
    for index in order:
        movable = {body for body in pairs[index] if body >= num_reserved}
        free = [c for c in range(num_colours) if len(colours[c]) < width and not (movable & used[c])]
        if not free:
            return None
        best = min(free, key=lambda c: len(colours[c]))
        colours[best].append(int(index))
        used[best].update(movable)
    return [sorted(colour) for colour in colours]


def _balanced_edge_colouring(pairs: list[tuple[int, int]], num_reserved: int) -> list[list[int]]:
    """Fewest colours (then narrowest) such that no movable body occurs twice in a colour; deterministic."""
    if not pairs:
        return []
    degree: dict[int, int] = {}
    for pair in pairs:
        for body in pair:
            if body >= num_reserved:
                degree[body] = degree.get(body, 0) + 1
    rng = np.random.default_rng(0)
    num_colours = max(degree.values())
    while True:
        base_width = -(-len(pairs) // num_colours)
        for width in range(base_width, base_width + 3):
            for _ in range(COLOURING_ATTEMPTS):
                colours = _try_colouring(pairs, rng.permutation(len(pairs)), num_reserved, num_colours, width)
                if colours is not None:
                    return colours
        num_colours += 1


def _jax2d_kinds(num_polygon_polygon: int, polygon_circle: list[tuple[int, int]], num_circle_circle: int):
    """One colour per kind of pair in Jax2D's pair order (circle-polygon pairs by circle, then polygon)."""
    first_circle = num_polygon_polygon + len(polygon_circle)
    kinds = [
        list(range(num_polygon_polygon)),
        sorted(range(num_polygon_polygon, first_circle), key=lambda k: polygon_circle[k - num_polygon_polygon][::-1]),
        list(range(first_circle, first_circle + num_circle_circle)),
    ]
    return [kind for kind in kinds if kind]


@functools.cache
def pair_layout(static: StaticSimParams) -> PairLayout:
    """The candidate pairs of `static` and their solver colours (cached per static params)."""
    p, n, reserved = static.num_polygons, static.num_bodies, static.num_reserved_static
    polygon_polygon = [(a, b) for a in range(p) for b in range(a + 1, p) if b >= reserved]
    polygon_circle = [(a, b) for a in range(p) for b in range(p, n)]
    circle_circle = [(a, b) for a in range(p, n) for b in range(a + 1, n)]
    pairs = polygon_polygon + polygon_circle + circle_circle
    if static.contact_order == ContactOrder.JAX2D:
        colours = _jax2d_kinds(len(polygon_polygon), polygon_circle, len(circle_circle))
    else:
        colours = _balanced_edge_colouring(pairs, reserved)
    width = max((len(c) for c in colours), default=0)
    colour_slots = np.full((len(colours), width), len(pairs), np.int32)
    for row, colour in enumerate(colours):
        colour_slots[row, : len(colour)] = colour  # in the colour's order
    pair_array = np.asarray(pairs, np.int32).reshape(-1, 2)
    padded_pairs = np.concatenate([pair_array, np.full((1, 2), n, np.int32)])
    return PairLayout(
        body_a=pair_array[:, 0],
        body_b=pair_array[:, 1],
        num_bodies=n,
        num_reserved_static=reserved,
        num_polygon_polygon=len(polygon_polygon),
        num_polygon_circle=len(polygon_circle),
        num_circle_circle=len(circle_circle),
        colour_slots=colour_slots,
        colour_body_a=padded_pairs[colour_slots, 0],
        colour_body_b=padded_pairs[colour_slots, 1],
    )
