"""Narrowphase: contact manifolds (normal, up to 2 points, separations, feature ids) for every candidate pair."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from flax import struct

from kforge.engine.geometry import dot2, norm2, rotate
from kforge.engine.pairs import PairLayout
from kforge.engine.params import MAX_POLYGON_VERTICES
from kforge.engine.state import NO_FEATURE, Bodies

REFERENCE_FACE_TOLERANCE = 5e-4
"""[m] polygon B's face becomes the reference only if it separates more than A's by this (avoids flip-flopping)."""

KINETIX_REFERENCE_FACE_TOLERANCE = 1e-2
"""[m] the same tolerance in Jax2D's polygon pairs (`CollisionRules.JAX2D`)."""

DIRECTION_EPSILON = 1e-9
"""[m] below this distance a direction is undefined and a fixed fallback is used."""


@struct.dataclass
class Manifolds:
    """Contact manifolds of all K candidate pairs; normals point from body_a to body_b."""

    normal: jnp.ndarray  # (K, 2) unit
    point: jnp.ndarray  # (K, 2, 2) [m] world contact points, midway between the two surfaces
    separation: jnp.ndarray  # (K, 2) [m] negative when overlapping
    valid: jnp.ndarray  # (K, 2) bool: point exists (closer than the pair's speculative margin)
    feature: jnp.ndarray  # (K, 2) i32 geometric feature id of the point, for warm starting


@struct.dataclass
class WorldGeometry:
    """Per-body geometry in world coordinates, computed once per step."""

    vertices: jnp.ndarray  # (N, 4, 2) [m]; for triangles the 4th vertex repeats the 1st
    normals: jnp.ndarray  # (N, 4, 2) outward unit normal of edge i (vertex i -> i+1)
    edge_valid: jnp.ndarray  # (N, 4) bool
    next_vertex: jnp.ndarray  # (N, 4) i32 index of the vertex after i
    centre: jnp.ndarray  # (N, 2) [m]
    radius: jnp.ndarray  # (N,) [m] circle radius (0 for polygons)


def world_geometry(bodies: Bodies) -> WorldGeometry:
    """World-frame vertices and edge normals of every body."""
    index = jnp.arange(MAX_POLYGON_VERTICES)
    n = bodies.n_vertices[:, None]
    edge_valid = index < n
    next_vertex = jnp.where(index + 1 < n, index + 1, 0)
    local = jnp.where(edge_valid[..., None], bodies.vertices, bodies.vertices[:, :1])
    world = bodies.position[:, None, :] + rotate(bodies.rotation[:, None], local)
    edge = jnp.take_along_axis(world, next_vertex[..., None], axis=1) - world
    length = norm2(edge)[..., None]
    normals = jnp.stack([edge[..., 1], -edge[..., 0]], -1) / jnp.maximum(length, DIRECTION_EPSILON)
    return WorldGeometry(world, normals, edge_valid, next_vertex, bodies.position, bodies.radius)


def _take(tree, index):
    return jax.tree_util.tree_map(lambda x: x[index], tree)


def _best_edge(normals, vertices, edge_valid, other_vertices):
    """Largest separation of `other` from any valid edge of this polygon, and that edge's index."""
    offset = dot2(normals, vertices)
    projection = [dot2(normals, other_vertices[j]) - offset for j in range(other_vertices.shape[0])]
    separation = jnp.where(edge_valid, functools.reduce(jnp.minimum, projection), -jnp.inf)
    edge = jnp.argmax(separation)
    return separation[edge], edge


def _clip(segment, ids, plane_normal, offset, clip_id):
    """Keep the part of `segment` (p1, p2) with dot(plane_normal, x) <= offset; returns its points, their ids (`ids`, or
    `clip_id` for a point moved onto the plane), and whether any of it is kept."""
    (p1, p2), (id1, id2) = segment, ids
    d1 = dot2(plane_normal, p1) - offset
    d2 = dot2(plane_normal, p2) - offset
    crossing = p1 + (d1 / jnp.where(d1 == d2, 1.0, d1 - d2)) * (p2 - p1)
    q1 = jnp.where(d1 <= 0, p1, crossing)
    q2 = jnp.where(d2 <= 0, p2, crossing)
    return (q1, q2), (jnp.where(d1 <= 0, id1, clip_id), jnp.where(d2 <= 0, id2, clip_id)), (d1 <= 0) | (d2 <= 0)


def _deepest_two(vertices, valid, normal):
    """Indices of the two valid vertices deepest along -normal, deepest first."""
    depth = jnp.where(valid, dot2(vertices, normal), jnp.inf)
    first = jnp.argmin(depth)
    second = jnp.argmin(depth.at[first].set(jnp.inf))
    return first, second


def _clamp_to_face(point, r1, tangent, length):
    """`point` moved along the face's tangent into the face's extent; True where it moved."""
    along = dot2(point - r1, tangent)
    clamped = jnp.clip(along, 0.0, length)
    return point + (clamped - along) * tangent, clamped != along


def _jax2d_incident_points(inc: WorldGeometry, normal, r1, tangent, length):
    """Jax2D's points of two polygons: the incident polygon's two deepest vertices, each moved along the reference
    face (from `r1` along `tangent`, `length` long) into its extent. Returns the points, whether they stand (always),
    the incident feature and the points' ids."""
    deepest, next_deepest = _deepest_two(inc.vertices, inc.edge_valid, normal)
    k1, moved1 = _clamp_to_face(inc.vertices[deepest], r1, tangent, length)
    k2, moved2 = _clamp_to_face(inc.vertices[next_deepest], r1, tangent, length)
    point_ids = jnp.stack(
        [
            jnp.where(moved1, MAX_POLYGON_VERTICES, deepest),
            jnp.where(moved2, MAX_POLYGON_VERTICES + 1, next_deepest),
        ]
    )
    return jnp.stack([k1, k2]), True, deepest, point_ids


def _clipped_incident_edge(inc: WorldGeometry, normal, face, tangent):
    """Box2D's points of two polygons: the incident edge most anti-parallel to the reference normal, clipped to the
    sides of the reference face `face` (r1, r2). Returns the points, whether both clips kept some of the edge, the
    incident edge and the points' ids."""
    r1, r2 = face
    inc_edge = jnp.argmin(jnp.where(inc.edge_valid, dot2(inc.normals, normal), jnp.inf))
    inc_next = inc.next_vertex[inc_edge]
    edge = (inc.vertices[inc_edge], inc.vertices[inc_next])
    edge, ids, ok1 = _clip(edge, (inc_edge, inc_next), -tangent, -dot2(tangent, r1), MAX_POLYGON_VERTICES)
    edge, ids, ok2 = _clip(edge, ids, tangent, dot2(tangent, r2), MAX_POLYGON_VERTICES + 1)
    return jnp.stack(edge), ok1 & ok2, inc_edge, jnp.stack(ids)


def polygon_polygon(
    a: WorldGeometry, b: WorldGeometry, margin, kinetix_points: bool = False, jax2d_geometry: bool = False
):
    """Manifold of two convex polygons: separating axes, then clipping of the incident edge to the reference face.

    With `kinetix_points` (static) the points lie on the incident polygon and every overlapping point takes the
    pair's deepest separation, as in Jax2D; with `jax2d_geometry` (static) the points are Jax2D's: the incident
    polygon's two deepest vertices moved along the reference face into its extent (`engine.CollisionRules.JAX2D`)."""
    separation_a, edge_a = _best_edge(a.normals, a.vertices, a.edge_valid, b.vertices)
    separation_b, edge_b = _best_edge(b.normals, b.vertices, b.edge_valid, a.vertices)
    tolerance = KINETIX_REFERENCE_FACE_TOLERANCE if jax2d_geometry else REFERENCE_FACE_TOLERANCE
    flip = separation_b > separation_a + tolerance
    ref = jax.tree_util.tree_map(lambda x, y: jnp.where(flip, y, x), a, b)
    inc = jax.tree_util.tree_map(lambda x, y: jnp.where(flip, x, y), a, b)
    ref_edge = jnp.where(flip, edge_b, edge_a)
    normal = ref.normals[ref_edge]
    r1, r2 = ref.vertices[ref_edge], ref.vertices[ref.next_vertex[ref_edge]]
    length = norm2(r2 - r1)
    tangent = (r2 - r1) / jnp.maximum(length, DIRECTION_EPSILON)

    if jax2d_geometry:
        points, clipped, incident_feature, point_ids = _jax2d_incident_points(inc, normal, r1, tangent, length)
    else:
        points, clipped, incident_feature, point_ids = _clipped_incident_edge(inc, normal, (r1, r2), tangent)
    separation = dot2(points, normal) - dot2(normal, r1)
    pair_separation = jnp.maximum(separation_a, separation_b)
    valid = clipped & (separation < margin) & (pair_separation < margin)
    if kinetix_points:
        placed = points
        separation = jnp.where(separation <= 0, pair_separation, separation)
    else:
        placed = points - 0.5 * separation[:, None] * normal
    base_id = ((flip.astype(jnp.int32) * MAX_POLYGON_VERTICES + ref_edge) * MAX_POLYGON_VERTICES + incident_feature) * 8
    ids = base_id + point_ids
    feature = jnp.where(valid, ids, NO_FEATURE)
    return jnp.where(flip, -normal, normal), placed, separation, valid, feature


def polygon_circle(
    a: WorldGeometry, b: WorldGeometry, margin, kinetix_points: bool = False, jax2d_geometry: bool = False
):
    """Manifold of a polygon (a) and a circle (b); one point, on the polygon's surface with `kinetix_points`; a circle
    whose centre is inside the polygon overlaps it by its radius with `jax2d_geometry`."""
    centre, radius = b.centre, b.radius
    face_distance = jnp.where(a.edge_valid, dot2(a.normals, centre - a.vertices), -jnp.inf)
    edge = jnp.argmax(face_distance)
    distance = face_distance[edge]
    v1, v2 = a.vertices[edge], a.vertices[a.next_vertex[edge]]
    before_v1 = dot2(centre - v1, v2 - v1) < 0
    after_v2 = dot2(centre - v2, v1 - v2) < 0
    corner = jnp.where(before_v1, v1, v2)
    to_centre = centre - corner
    corner_distance = norm2(to_centre)
    in_corner_region = (distance > 0) & (before_v1 | after_v2)
    corner_normal = to_centre / jnp.maximum(corner_distance, DIRECTION_EPSILON)
    normal = jnp.where(in_corner_region, corner_normal, a.normals[edge])
    separation = jnp.where(in_corner_region, corner_distance, distance) - radius
    point = centre - (radius + (separation if kinetix_points else 0.5 * separation)) * normal
    if jax2d_geometry:
        separation = jnp.where(distance < 0, -radius, separation)
    region = jnp.where(in_corner_region, jnp.where(before_v1, 1, 2), 0)
    valid = separation < margin
    return _one_point(normal, point, separation, valid, edge * 3 + region)


def circle_circle(a: WorldGeometry, b: WorldGeometry, margin, kinetix_points: bool = False):
    """Manifold of two circles; coincident centres separate along +y; the point on a's surface with
    `kinetix_points`."""
    offset = b.centre - a.centre
    distance = norm2(offset)
    normal = jnp.where(
        distance > DIRECTION_EPSILON, offset / jnp.maximum(distance, DIRECTION_EPSILON), jnp.array([0.0, 1.0])
    )
    separation = distance - a.radius - b.radius
    point = a.centre + (a.radius if kinetix_points else a.radius + 0.5 * separation) * normal
    return _one_point(normal, point, separation, separation < margin, jnp.int32(0))


def _one_point(normal, point, separation, valid, feature):
    return (
        normal,
        jnp.stack([point, point]),
        jnp.stack([separation, jnp.inf]),
        jnp.stack([valid, False]),
        jnp.stack([jnp.where(valid, feature, NO_FEATURE), NO_FEATURE]),
    )


def manifolds(
    geometry: WorldGeometry,
    layout: PairLayout,
    margin: jnp.ndarray,
    kinetix_points: bool = False,
    jax2d_geometry: bool = False,
) -> Manifolds:
    """Manifolds of all candidate pairs in layout order; `margin` (K,) [m] is each pair's speculative distance;
    `kinetix_points` (static) places the points as Jax2D does (`engine.ContactPoints.KINETIX`),
    `jax2d_geometry` (static) picks the points of two polygons and the depth of an engulfed circle as Jax2D
    does (`engine.CollisionRules.JAX2D`)."""
    laws = {"kinetix_points": kinetix_points}
    kinds = (
        (functools.partial(polygon_polygon, jax2d_geometry=jax2d_geometry, **laws), 0, layout.num_polygon_polygon),
        (
            functools.partial(polygon_circle, jax2d_geometry=jax2d_geometry, **laws),
            layout.num_polygon_polygon,
            layout.num_polygon_circle,
        ),
        (
            functools.partial(circle_circle, **laws),
            layout.num_polygon_polygon + layout.num_polygon_circle,
            layout.num_circle_circle,
        ),
    )
    parts = []
    for function, start, count in kinds:
        if count == 0:
            continue
        pair = slice(start, start + count)
        a = _take(geometry, layout.body_a[pair])
        b = _take(geometry, layout.body_b[pair])
        parts.append(jax.vmap(function)(a, b, margin[pair]))
    normal, point, separation, valid, feature = (jnp.concatenate(x) for x in zip(*parts, strict=True))
    return Manifolds(normal, point, separation, valid, feature.astype(jnp.int32))


def circle_contact_clearance(
    manifold: Manifolds, geometry: WorldGeometry, layout: PairLayout, velocity, acceleration, times
) -> jnp.ndarray:
    """(K,) bool: the pair has a circle, is apart at the start of the step, and free motion keeps the circle apart from
    the feature it faces (an edge, a corner, the other circle) at every time of `times` [s] and, for a point, at its
    closest approach.

    The contact normal of the step's start overstates how fast a circle closes on what it passes sideways: the
    corner it falls past, or an edge whose end it moves beyond. A circle beyond an edge's end and behind its line
    may meet the next edge, so is not counted as apart. `velocity` and `acceleration` (N, 3) are the bodies' at the
    start of the step; the feature moves with its body's velocity at the contact point (rotation to first order).
    """
    first = layout.num_polygon_polygon  # pairs from here on have a circle (polygon-circle, then circle-circle)
    if first == layout.body_a.shape[0]:
        return jnp.zeros(layout.body_a.shape[0], bool)
    a, b = layout.body_a[first:], layout.body_b[first:]
    is_circle_circle = jnp.arange(a.shape[0]) >= layout.num_polygon_circle
    feature = manifold.feature[first:, 0]
    region, edge = feature % 3, feature // 3  # polygon_circle's feature ids: edge * 3 + region (0: the edge's face)
    vertices, edge_valid = geometry.vertices[a], geometry.edge_valid[a]
    count = vertices.shape[1]
    # The faced edge's ends by selection over the edges (a gather with a per-scene index costs far more on CPU).
    after = [jnp.where(edge_valid[:, i + 1, None], vertices[:, i + 1], vertices[:, 0]) for i in range(count - 1)]
    after.append(vertices[:, 0])
    start = sum(jnp.where((edge == i)[:, None], vertices[:, i], 0.0) for i in range(count))
    end = sum(jnp.where((edge == i)[:, None], after[i], 0.0) for i in range(count))
    corner = jnp.where((region == 1)[:, None], start, end)
    point_like = is_circle_circle | (region != 0)
    centre_a = geometry.centre[a]
    start = jnp.where(is_circle_circle[:, None], centre_a, jnp.where(point_like[:, None], corner, start))
    end = jnp.where(point_like[:, None], start, end)
    reach = geometry.radius[a] + geometry.radius[b]  # a polygon's radius is 0
    lever = manifold.point[first:, 0] - centre_a

    def relative(per_body):
        at_a = per_body[a, :2] + per_body[a, 2:] * jnp.stack([-lever[:, 1], lever[:, 0]], -1)
        return tuple((per_body[b, :2] - at_a)[:, i] for i in range(2))

    # Component by component, as separate (K,) arrays.
    (vx, vy), (ax, ay) = relative(velocity), relative(acceleration)
    ox, oy = (geometry.centre[b, i] - start[:, i] for i in range(2))
    ex, ey = (end[:, i] - start[:, i] for i in range(2))
    nx, ny = manifold.normal[first:, 0], manifold.normal[first:, 1]
    inverse_length_squared = 1.0 / jnp.maximum(ex * ex + ey * ey, DIRECTION_EPSILON**2)

    def apart(px, py):
        along = (px * ex + py * ey) * inverse_length_squared
        beside = (along > 0.0) & (along < 1.0)
        nearest = jnp.clip(along, 0.0, 1.0)
        fx, fy = px - nearest * ex, py - nearest * ey
        height = nx * fx + ny * fy
        behind_a_face = ~point_like & (height <= 0)
        return jnp.where(beside, height > reach, (fx * fx + fy * fy > reach * reach) & ~behind_a_face)

    clear = manifold.separation[first:, 0] > 0
    for t in times:
        clear &= apart(ox + vx * t + 0.5 * ax * t**2, oy + vy * t + 0.5 * ay * t**2)
    closest_time = jnp.clip(-(ox * vx + oy * vy) / jnp.maximum(vx * vx + vy * vy, DIRECTION_EPSILON), 0.0, times[-1])
    clear &= ~point_like | apart(ox + vx * closest_time, oy + vy * closest_time)
    return jnp.concatenate([jnp.zeros(first, bool), clear])
