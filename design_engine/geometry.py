"""Reference geometry of a design: centroids, centroid-to-vertex vectors, mass properties.

Everything is differentiable in the design vector (the gradient of any objective flows through
the unit shapes and their masses). Lengths mm, areas mm^2, polar moments mm^4 (unit density).
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from design_engine._types import Array, DesignVector, Float, Points, Vertices
from design_engine.lattice import Lattice, vertex_offsets


class BlockGeometry(eqx.Module):
    """Reference (as-designed) geometry of every block.

    Attributes:
        centroids: [n_blocks, 2] area centroid c_b, mm.
        arms: [n_blocks, n_vertices, 2] centroid-to-vertex vectors d_bk, mm.
        areas: [n_blocks] polygon area, mm^2.
        polar_moments: [n_blocks] polar second moment about the centroid (unit density), mm^4.
    """

    centroids: Points
    arms: Vertices
    areas: Float[Array, " n_blocks"]
    polar_moments: Float[Array, " n_blocks"]


def polygon_properties(p: Float[Array, "n 2"]):
    """Area, area centroid and polar moment (about the centroid) of a CCW polygon (shoelace).

    Args:
        p: [n, 2] vertices in counter-clockwise order.

    Returns:
        (area [], centroid [2], polar moment []) for unit density.
    """
    q = jnp.roll(p, 1, axis=0)  # predecessor p_{k-1}
    c = q[:, 0] * p[:, 1] - q[:, 1] * p[:, 0]
    signed = 0.5 * jnp.sum(c)
    area = jnp.abs(signed)
    g = jnp.sum((q + p) * c[:, None], axis=0) / (6.0 * signed)
    pr, qr = p - g, q - g
    cr = qr[:, 0] * pr[:, 1] - qr[:, 1] * pr[:, 0]
    s = qr[:, 0] ** 2 + qr[:, 0] * pr[:, 0] + pr[:, 0] ** 2 + qr[:, 1] ** 2 + qr[:, 1] * pr[:, 1] + pr[:, 1] ** 2
    polar = jnp.abs(jnp.sum(cr * s)) / 12.0
    return area, g, polar


def block_geometry(lattice: Lattice, x: DesignVector) -> BlockGeometry:
    """Reference geometry of design `x` (mm) on `lattice`."""
    r = vertex_offsets(lattice, x)
    area, g, polar = jax.vmap(polygon_properties)(r)
    return BlockGeometry(
        centroids=jnp.asarray(lattice.grid_points, g.dtype) + g,
        arms=r - g[:, None, :],
        areas=area,
        polar_moments=polar,
    )


class InvalidDesignError(ValueError):
    """A design that cannot be simulated (wrong size, non-finite, inverted, self-intersecting or
    overlapping a neighbour)."""


def _segments_cross(p1, p2, p3, p4) -> bool:
    def orient(a, b, c):
        return (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])

    d1, d2 = orient(p3, p4, p1), orient(p3, p4, p2)
    d3, d4 = orient(p1, p2, p3), orient(p1, p2, p4)
    return (d1 * d2 < 0) and (d3 * d4 < 0)


def _polygons_intersect(a: np.ndarray, b: np.ndarray) -> bool:
    """Do polygons a [n, 2] and b [m, 2] share interior points (an edge crossing or one inside)?"""
    a1, a2 = a, np.roll(a, -1, axis=0)
    b1, b2 = b, np.roll(b, -1, axis=0)

    def orient(p, q, r):  # [.., 2] -> sign of the turn p -> q -> r
        return (q[..., 0] - p[..., 0]) * (r[..., 1] - p[..., 1]) - \
            (q[..., 1] - p[..., 1]) * (r[..., 0] - p[..., 0])

    A1, A2, B1, B2 = a1[:, None], a2[:, None], b1[None], b2[None]
    cross = (orient(B1, B2, A1) * orient(B1, B2, A2) < 0) & (orient(A1, A2, B1) * orient(A1, A2, B2) < 0)
    return bool(cross.any()) or _inside(a[0], b) or _inside(b[0], a)


def _inside(p: np.ndarray, poly: np.ndarray) -> bool:
    """Is point p [2] strictly inside polygon poly [n, 2] (even-odd rule)?"""
    x, y = poly[:, 0], poly[:, 1]
    xn, yn = np.roll(x, -1), np.roll(y, -1)
    up = (y > p[1]) != (yn > p[1])
    with np.errstate(divide="ignore", invalid="ignore"):
        xc = x + (p[1] - y) * (xn - x) / (yn - y)
    return bool(np.sum(up & (p[0] < xc)) % 2)


def first_overlap(polygons: np.ndarray) -> tuple[int, int] | None:
    """The first pair (a, b), a < b, of polygons [n, n_vertices, 2] that overlap, or None.

    Pairs are screened by bounding boxes, then tested exactly (edge crossings, containment).
    """
    lo, hi = polygons.min(axis=1), polygons.max(axis=1)
    i, j = np.triu_indices(polygons.shape[0], 1)
    near = np.all((lo[i] < hi[j]) & (lo[j] < hi[i]), axis=1)
    for a, b in zip(i[near], j[near]):
        if _polygons_intersect(polygons[a], polygons[b]):
            return int(a), int(b)
    return None


def check_design(lattice: Lattice, x) -> np.ndarray:
    """Validate a design vector before any simulation; returns it as float64 numpy (mm).

    Raises:
        InvalidDesignError: naming the first offending block and the reason.
    """
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 1 or x.size != lattice.n_design:
        raise InvalidDesignError(
            f"design vector has shape {x.shape}; this {lattice.kind} {lattice.shape[0]}x"
            f"{lattice.shape[1]} lattice needs {lattice.n_design} values"
        )
    if not np.all(np.isfinite(x)):
        raise InvalidDesignError(f"design vector holds {np.sum(~np.isfinite(x))} non-finite values")
    r = np.asarray(vertex_offsets(lattice, x))
    n = lattice.n_vertices
    for b in range(lattice.n_blocks):
        p = r[b]
        q = np.roll(p, 1, axis=0)
        signed = 0.5 * np.sum(q[:, 0] * p[:, 1] - q[:, 1] * p[:, 0])
        if signed <= 0.0:
            raise InvalidDesignError(
                f"block {b} is inverted or degenerate (signed area {signed:.4g} mm^2; vertices must "
                "stay counter-clockwise)"
            )
        if n > 3:
            for k in range(n):
                for m in range(k + 2, n):
                    if k == 0 and m == n - 1:
                        continue
                    if _segments_cross(p[k], p[(k + 1) % n], p[m], p[(m + 1) % n]):
                        raise InvalidDesignError(f"block {b} is self-intersecting (edges {k} and {m})")
    pair = first_overlap(np.asarray(lattice.grid_points, np.float64)[:, None, :] + r)
    if pair is not None:
        raise InvalidDesignError(
            f"block {pair[0]} overlaps block {pair[1]} in the reference geometry (units must not "
            "interpenetrate their neighbours)")
    return x
