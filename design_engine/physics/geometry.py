"""Reference geometry of a design: centroids, centroid-to-vertex vectors, mass properties.

Everything is differentiable in the design vector (the gradient of any objective flows through
the unit shapes and their masses). Lengths mm, areas mm^2, polar moments mm^4 (unit density).
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from design_engine._types import Array, DesignVector, Float, Points, Vertices
from design_engine.physics.lattice import Lattice, vertex_offsets
from metarig.polygon import first_overlap, self_crossings, signed_areas


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
    areas = signed_areas(r)
    crossings = (self_crossings(r) if lattice.n_vertices > 3
                 else np.full((lattice.n_blocks, 2), -1))
    bad = (areas <= 0.0) | (crossings[:, 0] >= 0)
    if bad.any():  # the first offending block, inversion before self-intersection
        b = int(np.argmax(bad))
        if areas[b] <= 0.0:
            raise InvalidDesignError(
                f"block {b} is inverted or degenerate (signed area {areas[b]:.4g} mm^2; vertices "
                "must stay counter-clockwise)"
            )
        raise InvalidDesignError(
            f"block {b} is self-intersecting (edges {crossings[b, 0]} and {crossings[b, 1]})")
    pair = first_overlap(np.asarray(lattice.grid_points, np.float64)[:, None, :] + r)
    if pair is not None:
        raise InvalidDesignError(
            f"block {pair[0]} overlaps block {pair[1]} in the reference geometry (units must not "
            "interpenetrate their neighbours)")
    return x
