"""Unit outlines for tracking: read `polygons_m` from a JSON file and validate it.

Accepted files: a plain `{"polygons_m": [[[x, y], ...], ...]}` or a design file written by the
design engine, which carries the same top-level key. The outlines are the reference
configuration in the sample frame (m), in unit-id order (row-major, x fastest).
"""

from pathlib import Path

import numpy as np

from metarig.polygon import self_intersecting, signed_areas
from tracking.jsonfile import read_json


class UnitsError(ValueError):
    """The unit outlines are missing or malformed (the message names the file and the unit)."""


def validate_polygons(polys, where: str = "polygons_m") -> np.ndarray:
    """Check outlines and return them as float64 [n_units, n_vertices, 2].

    Raises:
        UnitsError: ragged vertex counts, fewer than 3 vertices, non-finite values, zero area
            or a self-intersecting outline (naming `where` and the unit id).
    """
    if not isinstance(polys, (list, tuple, np.ndarray)) or len(polys) == 0:
        raise UnitsError(f"{where}: 'polygons_m' must be a non-empty list of polygons")
    counts = set()
    for k, p in enumerate(polys):
        try:
            arr = np.asarray(p, dtype=np.float64)
        except (TypeError, ValueError):
            raise UnitsError(f"{where}: unit {k} is not a list of [x, y] numbers") from None
        if arr.ndim != 2 or arr.shape[1] != 2:
            raise UnitsError(f"{where}: unit {k} must be a list of [x, y] pairs")
        counts.add(arr.shape[0])
    if len(counts) != 1:
        raise UnitsError(f"{where}: ragged outlines (vertex counts {sorted(counts)}); "
                         "all units need the same number of vertices")
    arr = np.asarray(polys, dtype=np.float64)
    if arr.shape[1] < 3:
        raise UnitsError(f"{where}: each unit needs at least 3 vertices, got {arr.shape[1]}")
    bad = np.flatnonzero(~np.all(np.isfinite(arr), axis=(1, 2)))
    if bad.size:
        raise UnitsError(f"{where}: unit {int(bad[0])} has non-finite coordinates")
    for k in range(arr.shape[0]):
        if self_intersecting(arr[k]):
            raise UnitsError(f"{where}: unit {k} outline is self-intersecting")
    areas = signed_areas(arr)
    scale = np.ptp(arr.reshape(-1, 2), axis=0).max() or 1.0
    bad = np.flatnonzero(np.abs(areas) <= 1e-12 * scale**2)
    if bad.size:
        raise UnitsError(f"{where}: unit {int(bad[0])} has zero area")
    return arr


def load_unit_polygons(path: str | Path) -> np.ndarray:
    """Read `polygons_m` [n_units, n_vertices, 2] (m, sample frame) from a JSON file."""
    path = Path(path)
    data = read_json(path, UnitsError, "units")
    if not isinstance(data, dict) or "polygons_m" not in data:
        raise UnitsError(f"{path}: no top-level key 'polygons_m' (unit outlines in metres)")
    return validate_polygons(data["polygons_m"], where=str(path))


# a ligament's two vertices are this close to its length apart (relative): the design engine
# moves both with one shift, so in the outlines every ligament keeps its length exactly
# (728 of 728 on the 24x16 focusing design; the nearest pair that is no ligament is 4e-5 off)
BOND_LENGTH_TOL = 1e-6


def bonds_from_outlines(polygons_m: np.ndarray, ligament_length_m: float | None = None
                        ) -> np.ndarray:
    """The lattice's ligaments found in its outlines: [nb, 4] int (unit a, vertex k, unit b,
    vertex l), a < b, for every pair of vertices of two units that lie the ligament length
    apart (within `BOND_LENGTH_TOL`). Without a length, the median distance of each vertex to
    the nearest vertex of another unit is taken (the ligaments, in a lattice bonded at its
    vertices). Empty [0, 4] when none is found."""
    p = np.asarray(polygons_m, np.float64)
    n, nv, _ = p.shape
    v = p.reshape(-1, 2)
    owner = np.repeat(np.arange(n), nv)

    def blocks():  # distances to every other unit's vertices, in blocks of rows
        for lo in range(0, v.shape[0], 1024):
            d = np.linalg.norm(v[lo:lo + 1024, None, :] - v[None, :, :], axis=-1)
            d[owner[lo:lo + 1024, None] == owner[None, :]] = np.inf
            yield lo, d

    length = ligament_length_m
    if length is None:
        length = float(np.median(np.concatenate([d.min(axis=1) for _, d in blocks()])))
    if not np.isfinite(length) or length <= 0:
        return np.zeros((0, 4), np.int64)
    i, j = [], []
    for lo, d in blocks():
        a, b = np.nonzero((np.abs(d - length) <= BOND_LENGTH_TOL * length)
                          & (owner[lo:lo + d.shape[0], None] < owner[None, :]))
        i.append(a + lo)
        j.append(b)
    i, j = np.concatenate(i), np.concatenate(j)
    return np.stack([owner[i], i % nv, owner[j], j % nv], axis=1).astype(np.int64)


def design_bonds(data, polygons_m: np.ndarray, where: str = "design") -> np.ndarray | None:
    """The ligaments of a parsed design (`bonds_from_outlines` at its
    `lattice.ligament_length_m`), None for one without a lattice (plain outlines).

    Raises:
        UnitsError: the ligament length is no positive number (naming `where`)."""
    lattice = data.get("lattice") if isinstance(data, dict) else None
    if not isinstance(lattice, dict) or "ligament_length_m" not in lattice:
        return None
    try:
        length = float(lattice["ligament_length_m"])
    except (TypeError, ValueError):
        length = float("nan")
    if not length > 0:
        raise UnitsError(f"{where}: lattice.ligament_length_m is not a positive number")
    return bonds_from_outlines(polygons_m, length)


def load_unit_bonds(path: str | Path, polygons_m: np.ndarray) -> np.ndarray | None:
    """The ligaments of a design file's lattice (`design_bonds`), None for a file without a
    lattice (plain outlines)."""
    return design_bonds(read_json(Path(path), UnitsError, "units"), polygons_m, str(path))
