"""Plane polygon geometry (numpy only): shoelace area and centroid, point-in-polygon, crossings.

Polygons are vertex arrays [..., n_vertices, 2], closed implicitly (the last vertex joins the
first). Any length unit; results are in the same unit. The differentiable JAX version used by the
design engine is `design_engine.physics.geometry.polygon_properties`.
"""

import numpy as np


def _cross(p: np.ndarray) -> np.ndarray:
    """x_k y_{k+1} - x_{k+1} y_k for every edge k of polygons p [..., nv, 2] -> [..., nv]."""
    q = np.roll(p, -1, axis=-2)
    return p[..., 0] * q[..., 1] - q[..., 0] * p[..., 1]


def signed_areas(polygons: np.ndarray) -> np.ndarray:
    """Signed shoelace areas [...] of polygons [..., nv, 2]: positive when counter-clockwise."""
    return 0.5 * _cross(np.asarray(polygons, dtype=np.float64)).sum(axis=-1)


def area_centroids(polygons: np.ndarray) -> np.ndarray:
    """Area centroids [..., 2] of simple polygons [..., nv, 2], either orientation (shoelace)."""
    p = np.asarray(polygons, dtype=np.float64)
    q = np.roll(p, -1, axis=-2)
    cross = _cross(p)
    six_a = 3.0 * cross.sum(axis=-1)  # 6 x signed area
    cx = ((p[..., 0] + q[..., 0]) * cross).sum(axis=-1) / six_a
    cy = ((p[..., 1] + q[..., 1]) * cross).sum(axis=-1) / six_a
    return np.stack([cx, cy], axis=-1)


def points_inside(x: np.ndarray, y: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """Even-odd point-in-polygon test of points (x, y) (broadcastable arrays) against one
    polygon [nv, 2] -> bool of the broadcast shape (a point exactly on an edge may go either
    way). Grid use: `points_inside(cols[None, :], rows[:, None], polygon)` -> [n_rows, n_cols]."""
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    inside = np.zeros(np.broadcast_shapes(x.shape, y.shape), dtype=bool)
    nv = polygon.shape[0]
    for a in range(nv):
        x1, y1 = polygon[a]
        x2, y2 = polygon[(a + 1) % nv]
        if y1 == y2:
            continue
        spans = (y > y1) != (y > y2)
        inside ^= spans & (x < x1 + (y - y1) * (x2 - x1) / (y2 - y1))
    return inside


def _orient(p: np.ndarray, q: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Twice the signed area of the triangles (p, q, r), points [..., 2] -> [...]."""
    return (q[..., 0] - p[..., 0]) * (r[..., 1] - p[..., 1]) - \
        (q[..., 1] - p[..., 1]) * (r[..., 0] - p[..., 0])


def edges_cross(a1, a2, b1, b2) -> np.ndarray:
    """Do segments a1-a2 and b1-b2 (points [..., 2]) cross at one interior point of both?
    Touching ends and collinear overlaps do not count."""
    return (_orient(b1, b2, a1) * _orient(b1, b2, a2) < 0) & \
        (_orient(a1, a2, b1) * _orient(a1, a2, b2) < 0)


def self_crossing(polygon: np.ndarray) -> tuple[int, int] | None:
    """The first pair of non-adjacent edges (k, m), k < m, of the closed polygon [nv, 2] that
    cross, or None (edge k runs from vertex k to vertex k + 1)."""
    p = np.asarray(polygon, dtype=np.float64)
    nv = p.shape[0]
    q = np.roll(p, -1, axis=0)
    for k in range(nv):
        for m in range(k + 2, nv):
            if k == 0 and m == nv - 1:
                continue  # adjacent edges share a vertex
            if edges_cross(p[k], q[k], p[m], q[m]):
                return k, m
    return None


def self_intersecting(polygon: np.ndarray) -> bool:
    """True when two non-adjacent edges of the closed polygon [nv, 2] cross."""
    return self_crossing(polygon) is not None


def polygons_overlap(a: np.ndarray, b: np.ndarray) -> bool:
    """Do simple polygons a [n, 2] and b [m, 2] share interior points (an edge crossing, or one
    inside the other)?"""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    a2, b2 = np.roll(a, -1, axis=0), np.roll(b, -1, axis=0)
    if edges_cross(a[:, None], a2[:, None], b[None], b2[None]).any():
        return True
    return bool(points_inside(a[0, 0], a[0, 1], b) or points_inside(b[0, 0], b[0, 1], a))


def first_overlap(polygons: np.ndarray) -> tuple[int, int] | None:
    """The first pair (i, j), i < j, of polygons [n, nv, 2] that overlap, or None. Pairs are
    screened by their bounding boxes, then tested exactly."""
    p = np.asarray(polygons, dtype=np.float64)
    lo, hi = p.min(axis=1), p.max(axis=1)
    i, j = np.triu_indices(p.shape[0], 1)
    near = np.all((lo[i] < hi[j]) & (lo[j] < hi[i]), axis=1)
    for a, b in zip(i[near], j[near]):
        if polygons_overlap(p[a], p[b]):
            return int(a), int(b)
    return None
