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
    """Even-odd point-in-polygon test of points (x, y) (broadcastable arrays) against polygons
    [..., nv, 2] whose leading shape broadcasts with them -> bool of the broadcast shape (a point
    exactly on an edge may go either way). Grid use, one polygon [nv, 2]:
    `points_inside(cols[None, :], rows[:, None], polygon)` -> [n_rows, n_cols]; one point per
    polygon [n, nv, 2]: x, y [n]."""
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    poly = np.asarray(polygon, dtype=np.float64)
    inside = np.zeros(np.broadcast_shapes(x.shape, y.shape, poly.shape[:-2]), dtype=bool)
    nv = poly.shape[-2]
    for a in range(nv):
        x1, y1 = poly[..., a, 0], poly[..., a, 1]
        x2, y2 = poly[..., (a + 1) % nv, 0], poly[..., (a + 1) % nv, 1]
        if poly.ndim == 2 and y1 == y2:  # one polygon's horizontal edge: no work on the points
            continue
        spans = (y > y1) != (y > y2)  # never for a horizontal edge
        dy = np.where(y1 == y2, 1.0, y2 - y1)
        inside ^= spans & (x < x1 + (y - y1) * (x2 - x1) / dy)
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


def _nonadjacent_edge_pairs(nv: int) -> tuple[np.ndarray, np.ndarray]:
    """Edge index pairs (k, m), k < m, of a closed polygon of nv vertices that share no vertex,
    in the order k, then m."""
    k, m = np.triu_indices(nv, 2)
    keep = ~((k == 0) & (m == nv - 1))
    return k[keep], m[keep]


def self_crossings(polygons: np.ndarray) -> np.ndarray:
    """[n, 2] for closed polygons [n, nv, 2]: the first pair of non-adjacent edges (k, m),
    k < m, of each that cross, or (-1, -1) (edge k runs from vertex k to vertex k + 1). All
    pairs of all polygons at once."""
    p = np.asarray(polygons, dtype=np.float64)
    q = np.roll(p, -1, axis=1)
    k, m = _nonadjacent_edge_pairs(p.shape[1])
    if k.size == 0:  # a triangle
        return np.full((p.shape[0], 2), -1)
    cross = edges_cross(p[:, k], q[:, k], p[:, m], q[:, m])  # [n, pairs]
    first = np.argmax(cross, axis=1)
    hit = cross[np.arange(p.shape[0]), first]
    return np.where(hit[:, None], np.stack([k[first], m[first]], axis=1), -1)


def self_crossing(polygon: np.ndarray) -> tuple[int, int] | None:
    """The first pair of non-adjacent edges (k, m), k < m, of the closed polygon [nv, 2] that
    cross, or None (edge k runs from vertex k to vertex k + 1)."""
    k, m = self_crossings(np.asarray(polygon)[None])[0]
    return None if k < 0 else (int(k), int(m))


def self_intersecting(polygon: np.ndarray) -> bool:
    """True when two non-adjacent edges of the closed polygon [nv, 2] cross."""
    return self_crossing(polygon) is not None


def _overlapping(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """[n] whether simple polygons a[k] [n, na, 2] and b[k] [n, nb, 2] share interior points (an
    edge crossing, or one inside the other)."""
    a2, b2 = np.roll(a, -1, axis=1), np.roll(b, -1, axis=1)
    crossing = edges_cross(a[:, :, None], a2[:, :, None], b[:, None], b2[:, None]).any(axis=(1, 2))
    return (crossing | points_inside(a[:, 0, 0], a[:, 0, 1], b)
            | points_inside(b[:, 0, 0], b[:, 0, 1], a))


def first_overlap(polygons: np.ndarray) -> tuple[int, int] | None:
    """The first pair (i, j), i < j, of polygons [n, nv, 2] that overlap, or None. Pairs are
    screened by their bounding boxes (sweeping them in order of their left edges, so that only
    boxes that meet in x are paired), then tested exactly, all at once."""
    p = np.asarray(polygons, dtype=np.float64)
    n = p.shape[0]
    lo, hi = p.min(axis=1), p.max(axis=1)
    order = np.argsort(lo[:, 0], kind="stable")
    # in that order, polygon k meets in x the next ones up to the first whose left edge is
    # at or past its right edge
    reach = np.searchsorted(lo[order, 0], hi[order, 0], side="left")
    count = np.maximum(reach - np.arange(n) - 1, 0)
    first = np.repeat(np.arange(n), count)
    offset = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
    a, b = order[first], order[first + 1 + offset]
    i, j = np.minimum(a, b), np.maximum(a, b)
    near = np.all((lo[i] < hi[j]) & (lo[j] < hi[i]), axis=1)
    i, j = i[near], j[near]
    hit = np.flatnonzero(_overlapping(p[i], p[j]))
    if not hit.size:
        return None
    k = hit[np.lexsort((j[hit], i[hit]))[0]]  # the first in (i, j) order
    return int(i[k]), int(j[k])
