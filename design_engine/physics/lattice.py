"""Lattice topology and the design-vector -> vertex map (spec sections 2 and 3.1).

A `Lattice` is static: counts, grid points, bonds. The design vector `x` (mm) holds one 2-vector
("shift") per group of vertices that must move together; every vertex is

    r_bk = base_offsets[b, k] + x.reshape(-1, 2)[shift_index[b, k]]

relative to its block's grid point. Both ends of every ligament take the same shift, which keeps
each ligament's rest length and orientation fixed for any `x` (no equality constraints needed).
Units of every length here: mm (engine-internal).
"""

import math
from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np

from design_engine._types import DesignVector, Vertices


@dataclass(frozen=True, eq=False)
class Lattice:
    """Static description of a rigid-unit network.

    Attributes:
        kind: "quads" (rotating squares) or "kagome" (triangles).
        shape: (nx, ny) units for quads, (n1, n2) cells for kagome.
        spacing: unit spacing s (quads) or cell size L (kagome), mm.
        ligament_length: ligament rest length l0, mm.
        grid_points: [n_blocks, 2] grid point of every block, mm.
        base_offsets: [n_blocks, n_vertices, 2] vertex offsets at x = 0, mm.
        shift_index: [n_blocks, n_vertices] row of x.reshape(-1, 2) each vertex takes.
        bonds: [n_bonds, 2] global node ids (n = n_vertices * block + k) of each ligament.
        bond_r0: [n_bonds, 2] reference ligament vector from node 0 to node 1, mm.
        cell_of_block: [n_blocks, 2] (column, row) of the grid cell that holds each block.
        min_vertex_angle: default lower bound of vertex angles, rad (30 deg quads, 10 deg kagome).
        unit_area_hat, unit_inertia_hat: unit-density area / polar moment of the reference unit
            divided by spacing^2 / spacing^4 (used for the design-independent damping).
    """

    kind: str
    shape: tuple[int, int]
    spacing: float
    ligament_length: float
    grid_points: np.ndarray
    base_offsets: np.ndarray
    shift_index: np.ndarray
    bonds: np.ndarray
    bond_r0: np.ndarray
    cell_of_block: np.ndarray
    min_vertex_angle: float
    unit_area_hat: float
    unit_inertia_hat: float

    @property
    def n_blocks(self) -> int:
        return int(self.grid_points.shape[0])

    @property
    def n_vertices(self) -> int:
        return int(self.base_offsets.shape[1])

    @property
    def n_bonds(self) -> int:
        return int(self.bonds.shape[0])

    @property
    def n_design(self) -> int:
        return 2 * int(self.shift_index.max() + 1)

    @property
    def bond_blocks(self) -> np.ndarray:
        """[n_bonds, 2] block ids at the two ends of each bond."""
        return self.bonds // self.n_vertices

    @property
    def bond_vertices(self) -> np.ndarray:
        """[n_bonds, 2] local vertex index k at the two ends of each bond."""
        return self.bonds % self.n_vertices


    def describe(self) -> dict:
        """JSON-ready description (SI lengths) that `lattice_from_description` inverts."""
        return {
            "kind": self.kind,
            "shape": list(self.shape),
            "spacing_m": self.spacing / 1e3,
            "ligament_length_m": self.ligament_length / 1e3,
        }


def vertex_offsets(lattice: Lattice, x: DesignVector) -> Vertices:
    """Vertices of every block relative to its grid point, [n_blocks, n_vertices, 2] mm."""
    shifts = jnp.reshape(x, (-1, 2))
    return jnp.asarray(lattice.base_offsets, x.dtype) + shifts[lattice.shift_index]


def quads(nx: int, ny: int, spacing: float = 15.0, ligament_length: float | None = None) -> Lattice:
    """Rotating-squares lattice of nx x ny units (spec 2.1). Lengths in mm."""
    if nx < 2 or ny < 2:
        raise ValueError(f"a quads lattice needs at least 2x2 units, got {nx}x{ny}")
    l0 = 0.15 * spacing if ligament_length is None else ligament_length
    if not 0.0 < l0 < spacing:
        raise ValueError(f"ligament length {l0} mm must lie in (0, spacing={spacing} mm)")
    a = 0.5 * (spacing - l0)
    n_h = (nx + 1) * ny  # shifts in H, indexed (i, j) with i in [0, nx], j in [0, ny)

    def h(i, j):
        return i * ny + j

    def v(i, j):
        return n_h + i * (ny + 1) + j

    nb = nx * ny
    grid = np.zeros((nb, 2))
    base = np.zeros((nb, 4, 2))
    sidx = np.zeros((nb, 4), dtype=np.int32)
    cell = np.zeros((nb, 2), dtype=np.int32)
    for j in range(ny):
        for i in range(nx):
            b = j * nx + i
            grid[b] = (i * spacing, j * spacing)
            base[b] = ((a, 0.0), (0.0, a), (-a, 0.0), (0.0, -a))
            sidx[b] = (h(i + 1, j), v(i, j + 1), h(i, j), v(i, j))
            cell[b] = (i, j)
    bonds, r0 = [], []
    for j in range(ny):
        for i in range(nx - 1):
            bonds.append((4 * (j * nx + i) + 0, 4 * (j * nx + i + 1) + 2))
            r0.append((l0, 0.0))
    for j in range(ny - 1):
        for i in range(nx):
            bonds.append((4 * (j * nx + i) + 1, 4 * ((j + 1) * nx + i) + 3))
            r0.append((0.0, l0))
    return Lattice(
        kind="quads",
        shape=(nx, ny),
        spacing=float(spacing),
        ligament_length=float(l0),
        grid_points=grid,
        base_offsets=base,
        shift_index=sidx,
        bonds=np.asarray(bonds, dtype=np.int32),
        bond_r0=np.asarray(r0),
        cell_of_block=cell,
        min_vertex_angle=math.radians(30.0),
        unit_area_hat=0.36125,
        unit_inertia_hat=0.02175026,
    )


def kagome(n1: int, n2: int, cell_size: float = 20.0, ligament_length: float = 2.25) -> Lattice:
    """Kagome-like triangle lattice of n1 x n2 rhombic cells, 2 triangles each (spec 2.3)."""
    if n1 < 2 or n2 < 2:
        raise ValueError(f"a kagome lattice needs at least 2x2 cells, got {n1}x{n2}")
    L, l0 = float(cell_size), float(ligament_length)
    a1 = np.array([L, 0.0])
    a2 = L * np.array([math.cos(math.pi / 3), math.sin(math.pi / 3)])
    c30, s30 = math.cos(math.pi / 6), math.sin(math.pi / 6)
    b_int = l0 * np.array([c30, s30])
    b_1 = l0 * np.array([0.0, -1.0])
    b_2 = l0 * np.array([-c30, s30])
    n_s1 = (n1 + 1) * n2
    n_s2 = n1 * (n2 + 1)

    def s1(i, j):
        return i * n2 + j

    def s2(i, j):
        return n_s1 + i * (n2 + 1) + j

    def s3(i, j):
        return n_s1 + n_s2 + i * n2 + j

    nb = 2 * n1 * n2
    grid = np.zeros((nb, 2))
    base = np.zeros((nb, 3, 2))
    sidx = np.zeros((nb, 3), dtype=np.int32)
    cell = np.zeros((nb, 2), dtype=np.int32)
    for j in range(n2):
        for i in range(n1):
            c = j * n1 + i
            origin = i * a1 + j * a2
            for b in (2 * c, 2 * c + 1):
                grid[b] = origin
                cell[b] = (i, j)
            base[2 * c] = (0.5 * a1 - 0.5 * b_1, 0.5 * (a1 + a2) - 0.5 * b_int, 0.5 * a2 - 0.5 * b_2)
            sidx[2 * c] = (s2(i, j), s3(i, j), s1(i, j))
            base[2 * c + 1] = (0.5 * (a1 + a2) + 0.5 * b_int, a1 + 0.5 * a2 + 0.5 * b_2,
                               0.5 * a1 + a2 + 0.5 * b_1)
            sidx[2 * c + 1] = (s3(i, j), s1(i + 1, j), s2(i, j + 1))
    bonds, r0 = [], []
    for c in range(n1 * n2):
        bonds.append((3 * (2 * c) + 1, 3 * (2 * c + 1) + 0))
        r0.append(b_int)
    for j in range(n2 - 1):
        for i in range(n1):
            bonds.append((3 * (2 * ((j + 1) * n1 + i)) + 0, 3 * (2 * (j * n1 + i) + 1) + 2))
            r0.append(b_1)
    for j in range(n2):
        for i in range(n1 - 1):
            bonds.append((3 * (2 * (j * n1 + i + 1)) + 2, 3 * (2 * (j * n1 + i) + 1) + 1))
            r0.append(b_2)
    return Lattice(
        kind="kagome",
        shape=(n1, n2),
        spacing=L,
        ligament_length=l0,
        grid_points=grid,
        base_offsets=base,
        shift_index=sidx,
        bonds=np.asarray(bonds, dtype=np.int32),
        bond_r0=np.asarray(r0),
        cell_of_block=cell,
        min_vertex_angle=math.radians(10.0),
        unit_area_hat=0.070175913225,
        unit_inertia_hat=9.477510275e-4,
    )


def lattice_from_description(desc: dict) -> Lattice:
    """Inverse of `Lattice.describe` (SI lengths in, mm inside)."""
    kind = desc.get("kind")
    shape = desc.get("shape")
    if kind not in ("quads", "kagome") or not (isinstance(shape, list) and len(shape) == 2):
        raise ValueError(f"lattice description needs kind in (quads, kagome) and shape [n, m]: {desc}")
    spacing = 1e3 * float(desc["spacing_m"])
    l0 = 1e3 * float(desc["ligament_length_m"])
    if kind == "quads":
        return quads(int(shape[0]), int(shape[1]), spacing, l0)
    return kagome(int(shape[0]), int(shape[1]), spacing, l0)


def periodic_design(lattice: Lattice, bias_angle: float) -> np.ndarray:
    """Periodic initial design x (mm), spec 2.2: rotated squares with bias angle (rad).

    Kagome lattices have no bias parametrisation; their periodic design is x = 0 (regular kagome),
    and a non-zero bias angle is rejected.
    """
    if lattice.kind == "kagome":
        if bias_angle != 0.0:
            raise ValueError("kagome lattices have no bias angle; use bias angle 0")
        return np.zeros(lattice.n_design)
    if not -math.pi / 4 < bias_angle < math.pi / 4:
        raise ValueError(f"bias angle {math.degrees(bias_angle):.1f} deg outside (-45, 45) deg")
    nx, ny = lattice.shape
    a = 0.5 * (lattice.spacing - lattice.ligament_length)
    hh = np.zeros((nx + 1, ny, 2))
    vv = np.zeros((nx, ny + 1, 2))
    for i in range(nx + 1):
        for j in range(ny):
            hh[i, j, 1] = a * math.tan((-1) ** (i + j) * bias_angle)
    for i in range(nx):
        for j in range(ny + 1):
            vv[i, j, 0] = -a * math.tan((-1) ** (i + j) * bias_angle)
    return np.concatenate([hh.ravel(), vv.ravel()])
