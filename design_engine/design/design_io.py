"""Design files: JSON with the lattice, the design vector and the unit outlines (SI).

Format `metarig-design/1`:
    {"format": "metarig-design/1",
     "lattice": {"kind": "quads", "shape": [24, 16], "spacing_m": 0.015, "ligament_length_m": 0.00225},
     "design_m": [...],        # design vector (spec 3.1 order), metres
     "polygons_m": [[[x, y], ...], ...]}   # reference outline of every unit, sample frame, metres
`polygons_m` is derived (written for readers such as the DIC tracker); `design_m` is the truth.
"""

import json
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from design_engine.physics.geometry import InvalidDesignError, block_geometry, check_design
from design_engine.physics.lattice import Lattice, lattice_from_description

FORMAT = "metarig-design/1"


def design_document(lattice: Lattice, x_mm, **extra) -> dict:
    """JSON-ready design document for design vector `x_mm` (mm) on `lattice`."""
    x = check_design(lattice, x_mm)
    g = block_geometry(lattice, jnp.asarray(x))
    polys = np.asarray(g.centroids[:, None, :] + g.arms) / 1e3
    doc = {"format": FORMAT, "lattice": lattice.describe(), "design_m": (x / 1e3).tolist(),
           "polygons_m": polys.tolist()}
    doc.update(extra)
    return doc


def save_design(path: str | Path, lattice: Lattice, x_mm, **extra) -> Path:
    """Write a design file; returns its path."""
    path = Path(path)
    path.write_text(json.dumps(design_document(lattice, x_mm, **extra)))
    return path


def load_design(path: str | Path) -> tuple[Lattice, np.ndarray]:
    """Read a design file -> (lattice, design vector in mm), validated.

    Raises:
        InvalidDesignError: with the file name, for unreadable or inconsistent files.
    """
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except FileNotFoundError:
        raise InvalidDesignError(f"design file {path} does not exist") from None
    except (OSError, ValueError) as exc:  # ValueError: not JSON, or bytes that are not text
        raise InvalidDesignError(f"design file {path} is not readable JSON: {exc}") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise InvalidDesignError(f"{path}: not a {FORMAT} design file (missing or wrong 'format')")
    try:
        lattice = lattice_from_description(doc["lattice"])
        x = np.asarray(doc["design_m"], dtype=np.float64) * 1e3
    except (KeyError, TypeError, ValueError) as exc:
        raise InvalidDesignError(f"{path}: malformed design file ({exc})") from None
    try:
        return lattice, check_design(lattice, x)
    except InvalidDesignError as exc:
        raise InvalidDesignError(f"{path}: {exc}") from None
