"""Exact mass properties of convex polygons and discs, and polygon checks."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from kforge.engine.params import MAX_POLYGON_VERTICES

MIN_POLYGON_AREA = 1e-6
"""[m^2] polygons smaller than this are degenerate."""

CONVEXITY_TOLERANCE = 1e-9
"""[m^2] cross products of consecutive edges above -this count as convex turns."""


def cross2(a, b):
    """z component of the cross product of 2-vectors (last axis)."""
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def dot2(a, b):
    """Dot product of 2-vectors (last axis), written out so that it compiles to elementwise code."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1]


def norm2(vector):
    """Euclidean length of 2-vectors (last axis)."""
    return jnp.sqrt(dot2(vector, vector))


def rotate(angle, vector):
    """Rotate (..., 2) vectors counter-clockwise by `angle` radians."""
    c, s = jnp.cos(angle), jnp.sin(angle)
    return jnp.stack([c * vector[..., 0] - s * vector[..., 1], s * vector[..., 0] + c * vector[..., 1]], -1)


def rotate_host(angle, vectors) -> np.ndarray:
    """Numpy (float64) version of `rotate`, for host-side scene building and rendering."""
    c, s = np.cos(angle)[..., None], np.sin(angle)[..., None]
    vectors = np.asarray(vectors, np.float64)
    x, y = vectors[..., :1], vectors[..., 1:]
    return np.concatenate([c * x - s * y, s * x + c * y], -1)


def polygon_mass_properties(vertices, n_vertices, density):
    """Mass [kg], area centroid (2,) [m] and inertia about the centroid [kg m^2] of a convex polygon.

    `vertices` (4, 2) in any frame, counter-clockwise; only the first `n_vertices` are used.
    """
    index = jnp.arange(MAX_POLYGON_VERTICES)
    valid = index < n_vertices
    following = jnp.where(index + 1 < n_vertices, index + 1, 0)
    v0, v1 = vertices, vertices[following]
    # Triangles (origin, v0, v1): signed doubled areas, centroid and second-moment sums.
    doubled_area = jnp.where(valid, cross2(v0, v1), 0.0)
    area = 0.5 * jnp.sum(doubled_area)
    centroid = jnp.sum(doubled_area[:, None] * (v0 + v1), axis=0) / (3.0 * jnp.sum(doubled_area))
    second_moment = jnp.sum(doubled_area * (jnp.sum(v0 * v0, -1) + jnp.sum(v0 * v1, -1) + jnp.sum(v1 * v1, -1))) / 12.0
    mass = density * area
    inertia_about_origin = density * second_moment
    inertia = inertia_about_origin - mass * jnp.sum(centroid * centroid)
    return mass, centroid, inertia


def circle_mass_properties(radius, density):
    """Mass [kg] and inertia about the centre [kg m^2] of a disc: m = rho pi r^2, I = m r^2 / 2."""
    mass = density * jnp.pi * radius**2
    return mass, 0.5 * mass * radius**2


def check_convex_polygon(vertices: np.ndarray) -> np.ndarray:
    """Counter-clockwise float64 copy of a convex polygon's (n, 2) vertices; ValueError if it is not one."""
    vertices = np.asarray(vertices, np.float64)
    if vertices.ndim != 2 or vertices.shape[1] != 2 or not 3 <= vertices.shape[0] <= MAX_POLYGON_VERTICES:
        raise ValueError(
            f"polygon needs 3 to {MAX_POLYGON_VERTICES} vertices of shape (n, 2), got shape {vertices.shape}"
        )
    if not np.all(np.isfinite(vertices)):
        raise ValueError(f"polygon vertices must be finite, got {vertices.tolist()}")
    edges = np.roll(vertices, -1, axis=0) - vertices
    doubled_area = float(
        np.sum(vertices[:, 0] * np.roll(vertices, -1, 0)[:, 1] - vertices[:, 1] * np.roll(vertices, -1, 0)[:, 0])
    )
    if abs(doubled_area) < 2 * MIN_POLYGON_AREA:
        raise ValueError(f"degenerate polygon (area {abs(doubled_area) / 2:.3g} m^2): {vertices.tolist()}")
    if doubled_area < 0:
        vertices = vertices[::-1].copy()
        edges = np.roll(vertices, -1, axis=0) - vertices
    turns = edges[:, 0] * np.roll(edges, -1, 0)[:, 1] - edges[:, 1] * np.roll(edges, -1, 0)[:, 0]
    if np.any(turns <= CONVEXITY_TOLERANCE):
        raise ValueError(f"polygon is not strictly convex: {vertices.tolist()}")
    return vertices
