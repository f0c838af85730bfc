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
