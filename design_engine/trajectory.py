"""The one trajectory schema shared by simulation, tracking and recording (SI units), and its file."""

from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass(frozen=True)
class Trajectory:
    """Per-unit planar motion sampled in time.

    Attributes:
        t: [n_t] sample times, s.
        q: [n_t, n_units, 3] displacement of each unit's area centroid (u, v in m) and its
            counter-clockwise rotation theta (rad), from the reference configuration.
        qdot: [n_t, n_units, 3] rates (m/s, m/s, rad/s).
    Unit ids are row-major with x fastest (kagome: 2 triangles per cell, cells row-major).
    """

    t: np.ndarray
    q: np.ndarray
    qdot: np.ndarray

    def __post_init__(self):
        nt = np.shape(self.t)[0]
        if np.ndim(self.q) != 3 or np.shape(self.q)[0] != nt or np.shape(self.q)[2] != 3:
            raise ValueError(f"q must be [n_t={nt}, n_units, 3], got {np.shape(self.q)}")
        if np.shape(self.qdot) != np.shape(self.q):
            raise ValueError(f"qdot shape {np.shape(self.qdot)} differs from q {np.shape(self.q)}")

    @property
    def n_units(self) -> int:
        return int(self.q.shape[1])

    def save_npz(self, path: str | Path, **extra) -> Path:
        """Write `t`, `q`, `qdot` (plus any extra arrays) to a compressed .npz file."""
        path = Path(path)
        np.savez_compressed(path, t=self.t, q=self.q, qdot=self.qdot, **extra)
        return path

    @classmethod
    def load_npz(cls, path: str | Path) -> "Trajectory":
        """Read a trajectory written by `save_npz` (or by `metarig track`)."""
        with np.load(path) as f:
            missing = {"t", "q"} - set(f.files)
            if missing:
                raise ValueError(f"{path}: not a trajectory file (missing {sorted(missing)})")
            qdot = f["qdot"] if "qdot" in f.files else np.full_like(f["q"], np.nan)
            return cls(t=f["t"], q=f["q"], qdot=qdot)
