"""Manufacturability constraints g(x) <= 0 and their Jacobians (spec 3.2).

Three vector constraints, as NLopt takes them:
- angles: [4 n_bonds] = [a_min - void1, a_min - void2, b_min - vertex1, b_min - vertex2] (rad);
- edges: [n_blocks * n_vertices] = e_min - edge length (mm), block-major;
- free vertices: [n_free_vertices] = b_min - vertex angle (rad) at the vertices no ligament joins
  (a boundary unit's outer corners, `free_vertices`). The spec bounds the vertex angle at bonded
  vertices only; at an outer corner nothing did, and MMA closed one to 0 and swung it across the
  unit's opposite edge (a self-intersecting unit, not simulated: focusing runs from seeded starts
  stalled against that wall, README "The optimisation-level charts with the native Verlet
  stages"). The same bound b_min holds every corner of a unit. With every corner at b_min or
  more, no corner can close from the reflex side either: a simple unit's corners sum to
  (n - 2) pi, so each stays at most (n - 2) pi - (n - 1) b_min (quads: 270 deg at 30 deg).

Void angles are wrapped onto [-b_min, 2 pi - b_min) before the check. A feasible void lies in
[0, 2 pi - 2 b_min], so the branch cut sits in the impossible range and an overlapping (negative)
void angle is caught. The reference code wraps onto [0, 2 pi), which makes the void check vacuous;
`reference_void_wrap=True` reproduces that for regression only.
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from scipy import sparse

from design_engine._types import Array, DesignVector, Float
from design_engine.physics.angles import bond_angles, edge_vectors, signed_angle
from design_engine.physics.geometry import block_geometry
from design_engine.physics.lattice import Lattice

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


def free_vertices(lattice: Lattice) -> np.ndarray:
    """[n_free_vertices, 2] (block, vertex) of the vertices no ligament joins, block-major."""
    bonded = np.zeros((lattice.n_blocks, lattice.n_vertices), bool)
    bb, bv = np.asarray(lattice.bond_blocks), np.asarray(lattice.bond_vertices)
    bonded[bb[:, 0], bv[:, 0]] = True
    bonded[bb[:, 1], bv[:, 1]] = True
    return np.argwhere(~bonded)


def constraint_rows(lattice: Lattice) -> dict[str, slice]:
    """The rows of each constraint in the stacked values (`all_constraints`), in their order:
    "angles" ([void 1; void 2; vertex 1; vertex 2], each over the ligaments), "edges"
    (block-major, [n_blocks, n_vertices]), "free_vertices" (in `free_vertices` order): the
    one home of the layout that `constraint_pattern` and `active_constraint_masks` read."""
    sizes = {"angles": 4 * lattice.n_bonds, "edges": lattice.n_blocks * lattice.n_vertices,
             "free_vertices": len(free_vertices(lattice))}
    rows, start = {}, 0
    for name, size in sizes.items():
        rows[name] = slice(start, start + size)
        start += size
    return rows


def constraint_count(lattice: Lattice) -> int:
    """How many components the stacked constraints have (`all_constraints`)."""
    return constraint_rows(lattice)["free_vertices"].stop


def free_vertex_constraints(lattice: Lattice, x: DesignVector,
                            limits: ConstraintLimits) -> Float[Array, " m"]:
    """Vertex-angle constraint values at the free vertices [n_free_vertices], rad; feasible where
    <= 0 (the angle measured as at a bonded vertex, angle(e+ -> e-) on [0, 2 pi))."""
    fv = free_vertices(lattice)
    e_plus, e_minus = edge_vectors(block_geometry(lattice, x).arms)
    beta = signed_angle(e_plus[fv[:, 0], fv[:, 1]], e_minus[fv[:, 0], fv[:, 1]])
    return limits.min_vertex_angle - jnp.mod(beta, TWO_PI)


def all_constraints(lattice: Lattice, x: DesignVector, limits: ConstraintLimits):
    """The stacked constraint values [angles (rad); edges (mm); free vertices (rad)]."""
    return jnp.concatenate([angle_constraints(lattice, x, limits),
                            edge_constraints(lattice, x, limits),
                            free_vertex_constraints(lattice, x, limits)])


def make_constraints(lattice: Lattice, limits: ConstraintLimits):
    """Jitted value-and-Jacobian functions `(x) -> (g [m], dg/dx [m, n])` for the three
    constraints (angles, edges, free vertices)."""

    def with_jac(fn):
        f = lambda x: fn(lattice, x, limits)  # noqa: E731
        return jax.jit(lambda x: (f(x), jax.jacrev(f)(x)))

    return (with_jac(angle_constraints), with_jac(edge_constraints),
            with_jac(free_vertex_constraints))


def constraint_pattern(lattice: Lattice) -> tuple[np.ndarray, np.ndarray]:
    """Structural non-zeros (rows, cols) of the stacked [angles; edges; free vertices] Jacobian
    over x.

    Every constraint is a function of the vertices of at most two units (the two ends of a
    ligament, or one unit's edges), and a unit's vertices move with its `shift_index` rows of x.
    """
    per_block = [np.sort(np.concatenate([2 * r, 2 * r + 1])) for r in lattice.shift_index]
    bb = lattice.bond_blocks
    layout = constraint_rows(lattice)
    rows, cols = [], []
    for r in range(layout["angles"].stop):
        b1, b2 = bb[r % lattice.n_bonds]
        c = np.union1d(per_block[b1], per_block[b2])
        rows.append(np.full(c.size, r))
        cols.append(c)
    edge_blocks = np.repeat(np.arange(lattice.n_blocks), lattice.n_vertices)
    free_blocks = free_vertices(lattice)[:, 0]
    for name, blocks in (("edges", edge_blocks), ("free_vertices", free_blocks)):
        for r, b in zip(range(layout[name].start, layout[name].stop), blocks):
            rows.append(np.full(per_block[b].size, r))
            cols.append(per_block[b])
    return np.concatenate(rows), np.concatenate(cols)


def _colour_columns(rows: np.ndarray, cols: np.ndarray, n_rows: int, n_cols: int) -> np.ndarray:
    """Greedy colouring of columns so that no two columns of one colour share a row."""
    p = sparse.csr_matrix((np.ones(rows.size), (rows, cols)), shape=(n_rows, n_cols))
    conflict = (p.T @ p).tocsr()
    colour = np.full(n_cols, -1, dtype=np.int64)
    for j in range(n_cols):
        used = colour[conflict.indices[conflict.indptr[j]:conflict.indptr[j + 1]]]
        free = np.setdiff1d(np.arange(used.size + 1), used[used >= 0])
        colour[j] = free[0]
    return colour


def make_sparse_constraints(lattice: Lattice, limits: ConstraintLimits, x_base, free):
    """Constraint values and sparse Jacobian over the free design variables.

    Args:
        lattice, limits: as `make_constraints`.
        x_base: [n_design] design (mm) that supplies the frozen variables.
        free: [n_free] indices of x the optimiser moves.

    Returns:
        `fn(x_free [n_free]) -> (g [m] numpy, J scipy.sparse.csr_matrix [m, n_free])` with g the
        stacked [angles (rad); edges (mm); free vertices (rad)] constraints. The Jacobian is exact: forward-mode
        products along one seed per column colour (columns that share no constraint share a
        seed), about 40 products instead of one reverse pass per constraint.
    """
    free = np.asarray(free)
    base = jnp.asarray(x_base, jnp.float64)
    n_free = free.size
    rows, cols = constraint_pattern(lattice)
    where = np.full(lattice.n_design, -1)
    where[free] = np.arange(n_free)
    keep = where[cols] >= 0
    rows, cols = rows[keep], where[cols[keep]]
    m = constraint_count(lattice)
    colour = _colour_columns(rows, cols, m, n_free)
    seeds = jnp.asarray(np.eye(int(colour.max()) + 1)[colour])  # [n_free, n_colours]

    def g(xf):
        return all_constraints(lattice, base.at[free].set(xf), limits)

    @jax.jit
    def value_and_compressed(xf):
        val, jvp_one = jax.linearize(g, xf)
        return val, jax.vmap(jvp_one, in_axes=1, out_axes=1)(seeds)

    pick = (jnp.asarray(rows), jnp.asarray(colour[cols]))

    def fn(xf):
        val, comp = value_and_compressed(jnp.asarray(xf, jnp.float64))
        data = np.asarray(comp[pick])
        return np.asarray(val), sparse.csr_matrix((data, (rows, cols)), shape=(m, n_free))

    return fn


def active_constraint_masks(lattice: Lattice, g: np.ndarray, tol: float = 1e-3) -> dict:
    """Which constraints are active (g >= -tol, rad or mm) in the stacked [angles; edges; free
    vertices] values.

    Returns dict with `voids` [n_bonds] bool (either void angle of a ligament), `vertices`
    [n_blocks, n_vertices] bool (vertex-angle constraint, at a bonded or a free vertex), `edges`
    [n_blocks, n_vertices] bool (edge k joins vertex k-1 and vertex k), and `counts`.
    """
    g = np.asarray(g)
    nb, nv, n_bonds = lattice.n_blocks, lattice.n_vertices, lattice.n_bonds
    act = g >= -tol
    layout = constraint_rows(lattice)
    a1, a2, b1, b2 = act[layout["angles"]].reshape(4, n_bonds)
    vertices = np.zeros((nb, nv), bool)
    bb, bv = lattice.bond_blocks, lattice.bond_vertices
    vertices[bb[b1, 0], bv[b1, 0]] = True
    vertices[bb[b2, 1], bv[b2, 1]] = True
    edges = act[layout["edges"]].reshape(nb, nv)
    fv = free_vertices(lattice)
    free_act = act[layout["free_vertices"]]
    vertices[fv[free_act, 0], fv[free_act, 1]] = True
    voids = a1 | a2
    return {"voids": voids, "vertices": vertices, "edges": edges,
            "counts": {"void_angle": int(a1.sum() + a2.sum()),
                       "vertex_angle": int(b1.sum() + b2.sum()), "edge_length": int(edges.sum()),
                       "free_vertex_angle": int(free_act.sum())}}
