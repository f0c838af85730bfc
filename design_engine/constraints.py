"""Manufacturability constraints g(x) <= 0 and their Jacobians (spec 3.2).

Two vector constraints, as NLopt takes them:
- angles: [4 n_bonds] = [a_min - void1, a_min - void2, b_min - vertex1, b_min - vertex2] (rad);
- edges: [n_blocks * n_vertices] = e_min - edge length (mm), block-major.

Void angles are wrapped onto [-b_min, 2 pi - b_min) before the check. A feasible void lies in
[0, 2 pi - 2 b_min], so the branch cut sits in the impossible range and an overlapping (negative)
void angle is caught. The reference code wraps onto [0, 2 pi), which makes the void check vacuous;
`reference_void_wrap=True` reproduces that for regression only.
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp

from design_engine._types import Array, DesignVector, Float
from design_engine.angles import bond_angles
from design_engine.geometry import block_geometry
from design_engine.lattice import Lattice

TWO_PI = 2.0 * math.pi


class ConstraintLimits(eqx.Module):
    """Bounds of the manufacturability constraints (rad, rad, mm)."""

    min_void_angle: float = 0.0
    min_vertex_angle: float = math.radians(30.0)
    min_edge_length: float = 3.0
    reference_void_wrap: bool = eqx.field(static=True, default=False)

    @classmethod
    def for_lattice(cls, lattice: Lattice, **overrides) -> "ConstraintLimits":
        """Defaults of the paper for this lattice kind (vertex angle 30 deg quads, 10 deg kagome)."""
        kw = {"min_vertex_angle": lattice.min_vertex_angle}
        kw.update(overrides)
        return cls(**kw)


def angle_constraints(lattice: Lattice, x: DesignVector, limits: ConstraintLimits) -> Float[Array, " m"]:
    """Angle constraint values [4 n_bonds], rad; feasible where <= 0."""
    ang = bond_angles(lattice, block_geometry(lattice, x).arms)
    if limits.reference_void_wrap:
        void1, void2 = jnp.mod(ang["alpha1"], TWO_PI), jnp.mod(ang["alpha2"], TWO_PI)
    else:
        lo = limits.min_vertex_angle
        void1 = jnp.mod(ang["alpha1"] + lo, TWO_PI) - lo
        void2 = jnp.mod(ang["alpha2"] + lo, TWO_PI) - lo
    vert1, vert2 = jnp.mod(ang["beta1"], TWO_PI), jnp.mod(ang["beta2"], TWO_PI)
    return jnp.concatenate([
        limits.min_void_angle - void1,
        limits.min_void_angle - void2,
        limits.min_vertex_angle - vert1,
        limits.min_vertex_angle - vert2,
    ])


def edge_constraints(lattice: Lattice, x: DesignVector, limits: ConstraintLimits) -> Float[Array, " m"]:
    """Edge-length constraint values [n_blocks * n_vertices], mm; feasible where <= 0."""
    arms = block_geometry(lattice, x).arms
    edges = jnp.linalg.norm(jnp.roll(arms, 1, axis=1) - arms, axis=-1)
    return (limits.min_edge_length - edges).reshape(-1)


def make_constraints(lattice: Lattice, limits: ConstraintLimits):
    """Jitted value-and-Jacobian functions `(x) -> (g [m], dg/dx [m, n])` for both constraints."""

    def with_jac(fn):
        f = lambda x: fn(lattice, x, limits)  # noqa: E731
        return jax.jit(lambda x: (f(x), jax.jacrev(f)(x)))

    return with_jac(angle_constraints), with_jac(edge_constraints)
