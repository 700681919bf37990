"""Plane geometry for the world model: angles, polygons (islands) and line of sight.

Pure numpy, no state. A polygon is a sequence of at least three (x, y) vertices in order, either winding,
without a repeated closing vertex; its last vertex connects back to the first.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np


def as_polygon(polygon: Sequence[Sequence[float]] | np.ndarray) -> np.ndarray:
    """The vertices as an (N, 2) float array (N >= 3)."""
    vertices = np.asarray(polygon, dtype=float)
    if vertices.ndim != 2 or vertices.shape[1] != 2 or len(vertices) < 3:
        raise ValueError(f"a polygon needs at least 3 (x, y) vertices, got shape {vertices.shape}")
    return vertices


def _edges(vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Start and end points of every edge, closing edge last."""
    return vertices, np.concatenate((vertices[1:], vertices[:1]))


def _cross(origin: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """z of (a - origin) x (b - origin): > 0 when b lies left of the line origin -> a."""
    oa = a - origin
    ob = b - origin
    return oa[..., 0] * ob[..., 1] - oa[..., 1] * ob[..., 0]


def _within_box(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Whether p lies in the axis-aligned box spanned by a and b (closed)."""
    low = np.minimum(a, b)
    high = np.maximum(a, b)
    return np.all((p >= low) & (p <= high), axis=-1)


def segments_intersect(p1, p2, q1, q2) -> np.ndarray:
    """Whether the closed segments p1-p2 and q1-q2 share a point (touching counts).

    Broadcasts, so one segment can be tested against many (e.g. every edge of a polygon) at once.
    """
    p1, p2, q1, q2 = (np.asarray(x, dtype=float) for x in (p1, p2, q1, q2))
    d1 = _cross(q1, q2, p1)
    d2 = _cross(q1, q2, p2)
    d3 = _cross(p1, p2, q1)
    d4 = _cross(p1, p2, q2)
    proper = (d1 * d2 < 0) & (d3 * d4 < 0)
    touching = (
        ((d1 == 0) & _within_box(p1, q1, q2))
        | ((d2 == 0) & _within_box(p2, q1, q2))
        | ((d3 == 0) & _within_box(q1, p1, p2))
        | ((d4 == 0) & _within_box(q2, p1, p2))
    )
    return proper | touching


def point_on_boundary(point, polygon) -> bool:
    """Whether the point lies on an edge of the polygon (exactly, up to rounding of the cross product)."""
    vertices = as_polygon(polygon)
    start, end = _edges(vertices)
    p = np.asarray(point, dtype=float)
    scale = np.maximum(np.sum((end - start) ** 2, axis=1), 1.0)
    collinear = np.abs(_cross(start, end, p)) <= 1e-12 * scale
    return bool(np.any(collinear & _within_box(p, start, end)))


def point_in_polygon(point, polygon) -> bool:
    """Whether the point lies strictly inside the polygon (points on the boundary are outside).

    Crossing number: count the edges that a ray from the point towards +x crosses; odd means inside.
    """
    vertices = as_polygon(polygon)
    if point_on_boundary(point, vertices):
        return False
    return _odd_crossings(point, *_edges(vertices))


def _odd_crossings(point, start: np.ndarray, end: np.ndarray) -> bool:
    """Whether a ray from the point towards +x crosses the edges an odd number of times."""
    x, y = float(point[0]), float(point[1])
    # Half-open rule on y, so a ray through a vertex counts the two edges meeting there once in total.
    straddles = (start[:, 1] > y) != (end[:, 1] > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        x_at_y = start[:, 0] + (y - start[:, 1]) * (end[:, 0] - start[:, 0]) / (end[:, 1] - start[:, 1])
    return np.count_nonzero(straddles & (x_at_y > x)) % 2 == 1


def segment_intersects_polygon(a, b, polygon) -> bool:
    """Whether the segment a-b touches or crosses an edge of the polygon or has an end strictly inside it.

    This is the line-of-sight test: a segment that only grazes a corner counts as blocked.
    """
    vertices = as_polygon(polygon)
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    # Most sight lines pass nowhere near an island: disjoint bounding boxes settle it cheaply.
    if np.any(np.maximum(a, b) < vertices.min(axis=0)) or np.any(np.minimum(a, b) > vertices.max(axis=0)):
        return False
    start, end = _edges(vertices)
    if np.any(segments_intersect(a, b, start, end)):
        return True
    # No edge is met, so the segment is wholly inside or wholly outside, and `a` is off the boundary.
    return _odd_crossings(a, start, end)


def is_simple_polygon(polygon) -> bool:
    """Whether the polygon has non-zero area and no two non-neighbouring edges meet.

    Neighbouring edges that fold back onto each other, and zero-length edges (a repeated vertex), need no
    test of their own: with four or more edges either puts a vertex on a non-neighbouring edge, and with
    three it leaves no area.
    """
    vertices = as_polygon(polygon)
    n = len(vertices)
    start, end = _edges(vertices)
    twice_area = np.sum(start[:, 0] * end[:, 1] - end[:, 0] * start[:, 1])
    if twice_area == 0:
        return False
    for i in range(n - 2):
        # Edges i + 2 .. n - 1, except the closing edge when i = 0 (it shares vertex 0 with edge 0).
        others = slice(i + 2, n - 1 if i == 0 else n)
        if np.any(segments_intersect(start[i], end[i], start[others], end[others])):
            return False
    return True


def sample_boundary(polygon, spacing: float) -> np.ndarray:
    """Points on the polygon's boundary, `spacing` metres apart along each edge, as an (M, 2) array.

    Each edge contributes its start vertex and then a point every `spacing` metres; the last gap of an edge
    (up to the next vertex) is at most `spacing`. Vertices are therefore always included.
    """
    if not spacing > 0:
        raise ValueError(f"spacing must be positive, got {spacing}")
    vertices = as_polygon(polygon)
    start, end = _edges(vertices)
    pieces = []
    for a, b in zip(start, end):
        length = float(np.hypot(*(b - a)))
        if length == 0:
            continue
        # Distances 0, s, 2s, ... strictly below the edge length (the end vertex starts the next edge).
        count = max(1, math.ceil(length / spacing - 1e-9))
        along = np.arange(count) * spacing
        pieces.append(a + np.outer(along / length, b - a))
    return np.concatenate(pieces, axis=0)
