"""Unit sets on a lattice: target windows, driven edge units, corner clamps, stage rows (spec 7, 8)."""

import numpy as np

from design_engine.physics.lattice import Lattice

SIDES = ("left", "right", "bottom", "top")


def _span(n: int, size: int, offset: int) -> range:
    return range((n - size) // 2 + offset, (n + size) // 2 + offset)


def _blocks_in_cells(lattice: Lattice, cells: list[tuple[int, int]]) -> np.ndarray:
    lookup = {}
    for b, (i, j) in enumerate(lattice.cell_of_block.tolist()):
        lookup.setdefault((i, j), []).append(b)
    out = []
    for c in cells:
        if c not in lookup:
            raise ValueError(f"cell {c} lies outside the {lattice.shape[0]}x{lattice.shape[1]} lattice")
        out.extend(lookup[c])
    return np.asarray(sorted(out), dtype=np.int64)


def window(lattice: Lattice, size: tuple[int, int], offset: tuple[int, int]) -> np.ndarray:
    """Units of a (w, h) window offset (sx, sy) from the centre; kagome: both triangles per cell."""
    nx, ny = lattice.shape
    cols, rows = _span(nx, size[0], offset[0]), _span(ny, size[1], offset[1])
    if cols.start < 0 or rows.start < 0 or cols.stop > nx or rows.stop > ny:
        raise ValueError(f"region window {tuple(size)} at offset {tuple(offset)} does not fit the "
                         f"{nx}x{ny} lattice (columns {list(cols)}, rows {list(rows)})")
    return _blocks_in_cells(lattice, [(i, j) for j in rows for i in cols])


def row_units(lattice: Lattice, row: int) -> np.ndarray:
    """All units whose grid cell is in `row`, ordered by column (kagome: both triangles)."""
    return _blocks_in_cells(lattice, [(i, row) for i in range(lattice.shape[0])])


def driven_units(lattice: Lattice, side: str, count: int = 2, shift: int = 0) -> np.ndarray:
    """Units pushed by the input on `side` (spec 7.2), in increasing id order."""
    if side not in SIDES:
        raise ValueError(f"input side must be one of {SIDES}, got {side!r}")
    nx, ny = lattice.shape
    if lattice.kind == "kagome":
        if side != "left":
            raise ValueError("kagome scenes are driven from the left only")
        j0 = (ny - 2) // 2
        return np.asarray([2 * (j * nx) for j in (j0, j0 + 1)], dtype=np.int64)
    if side in ("left", "right"):
        col = 0 if side == "left" else nx - 1
        rows = _span(ny, count, shift)
        if rows.start < 0 or rows.stop > ny:
            raise ValueError(f"input rows {list(rows)} fall outside 0..{ny - 1}")
        return np.asarray([j * nx + col for j in rows], dtype=np.int64)
    row = 0 if side == "bottom" else ny - 1
    cols = _span(nx, count, shift)
    if cols.start < 0 or cols.stop > nx:
        raise ValueError(f"input columns {list(cols)} fall outside 0..{nx - 1}")
    return np.asarray([row * nx + i for i in cols], dtype=np.int64)


def corner_clamps(lattice: Lattice) -> np.ndarray:
    """Units fixed at the four corners (spec 7.3): three per corner for quads, kagome as specified."""
    nx, ny = lattice.shape
    if lattice.kind == "quads":
        n = nx * ny
        ids = [0, 1, nx, nx - 2, nx - 1, 2 * nx - 1, n - 2, n - 1, n - nx - 1, n - nx, n - nx + 1,
               n - 2 * nx]
        return np.asarray(sorted(set(ids)), dtype=np.int64)

    def a(i, j):
        return 2 * (j * nx + i)

    ids = [a(0, 0), a(1, 0), a(0, 1),
           a(nx - 2, 0), a(nx - 1, 0), a(nx - 1, 0) + 1, a(nx - 1, 1) + 1,
           a(nx - 2, ny - 1) + 1, a(nx - 1, ny - 1) + 1, a(nx - 1, ny - 2) + 1,
           a(0, ny - 1), a(0, ny - 1) + 1, a(1, ny - 1) + 1, a(0, ny - 2)]
    return np.asarray(sorted(set(ids)), dtype=np.int64)
