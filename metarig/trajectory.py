"""The one trajectory type of the project (numpy only, SI): simulation, rig, tracking, comparison.

A `Trajectory` holds per-unit planar motion sampled in time. Its file is a compressed `.npz`
with the keys `t`, `q`, `qdot` and, where known, `quality`, `lost`, `sigma` and `complete`; `save_npz`
writes it atomically and `load_npz` reads it back (also older files without the optional keys).

Poses travel over ROS as absolute positions in the sample frame (`UnitPose2DArray`: x, y,
theta); `to_absolute` / `from_absolute` are the one conversion between those and displacements,
and `from_pose_messages` turns a sequence of pose messages back into a `Trajectory`.
"""

import os
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from metarig.readback import READ_ERRORS

OPTIONAL_KEYS = ("quality", "lost")  # [n_t, n_units], where known
FILE_KEYS = (*OPTIONAL_KEYS, "sigma")  # the optional arrays of a trajectory file


class TrajectoryFileError(ValueError):
    """A file that is not a readable trajectory (the message names the file and the problem)."""


@dataclass(frozen=True)
class Trajectory:
    """Per-unit planar motion sampled in time.

    Attributes:
        t: [n_t] sample times, s.
        q: [n_t, n_units, 3] displacement of each unit's area centroid (u, v in m) and its
            counter-clockwise rotation theta (rad), from the reference configuration.
        qdot: [n_t, n_units, 3] rates (m/s, m/s, rad/s); NaN where not known.
        quality: [n_t, n_units] tracking score in [-1, 1] (1 best), or None (simulation).
        lost: [n_t, n_units] True where the unit was not tracked (its q is not valid), or None.
        complete: False when the source was cut short (an interrupted tracking run).
        sigma: [n_t, n_units, 3] standard error of q (m, m, rad; tracking), or None.
    Unit ids are row-major with x fastest (kagome: 2 triangles per cell, cells row-major).
    """

    t: np.ndarray
    q: np.ndarray
    qdot: np.ndarray
    quality: np.ndarray | None = None
    lost: np.ndarray | None = None
    complete: bool = True
    sigma: np.ndarray | None = None

    def __post_init__(self):
        nt = np.shape(self.t)[0] if np.ndim(self.t) == 1 else -1
        if nt < 0:
            raise ValueError(f"t must be [n_t], got shape {np.shape(self.t)}")
        if np.ndim(self.q) != 3 or np.shape(self.q)[0] != nt or np.shape(self.q)[2] != 3:
            raise ValueError(f"q must be [n_t={nt}, n_units, 3], got {np.shape(self.q)}")
        if np.shape(self.qdot) != np.shape(self.q):
            raise ValueError(f"qdot shape {np.shape(self.qdot)} differs from q {np.shape(self.q)}")
        for name in OPTIONAL_KEYS:
            a = getattr(self, name)
            if a is not None and np.shape(a) != np.shape(self.q)[:2]:
                raise ValueError(f"{name} must be [n_t, n_units] = {np.shape(self.q)[:2]}, "
                                 f"got {np.shape(a)}")
        if self.sigma is not None and np.shape(self.sigma) != np.shape(self.q):
            raise ValueError(f"sigma shape {np.shape(self.sigma)} differs from q "
                             f"{np.shape(self.q)}")

    @property
    def n_units(self) -> int:
        return int(self.q.shape[1])

    @property
    def n_t(self) -> int:
        return int(self.q.shape[0])

    @property
    def valid(self) -> np.ndarray:
        """[n_t, n_units] True where the pose is measured and finite."""
        ok = np.all(np.isfinite(self.q), axis=-1)
        return ok if self.lost is None else ok & ~np.asarray(self.lost, bool)

    @classmethod
    def from_positions(cls, t, q, quality=None, lost=None, complete: bool = True,
                       sigma=None) -> "Trajectory":
        """A trajectory whose rates are backward differences of q (NaN at the first sample and
        next to lost samples): what a camera measures."""
        t, q = np.asarray(t, np.float64), np.asarray(q, np.float64)
        return cls(t=t, q=q, qdot=backward_rates(t, q), quality=quality, lost=lost,
                   complete=complete, sigma=sigma)

    def window(self, start: int, stop: int | None = None) -> "Trajectory":
        """The samples [start, stop) (all arrays sliced alike)."""
        sl = slice(start, stop)
        return replace(self, t=self.t[sl], q=self.q[sl], qdot=self.qdot[sl],
                       quality=None if self.quality is None else self.quality[sl],
                       lost=None if self.lost is None else self.lost[sl],
                       sigma=None if self.sigma is None else self.sigma[sl])

    def save_npz(self, path: str | Path, **extra) -> Path:
        """Write the trajectory (plus any extra arrays) to a compressed .npz, atomically."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        arrays = {"t": self.t, "q": self.q, "qdot": self.qdot,
                  "complete": np.array(bool(self.complete))}
        arrays.update({k: getattr(self, k) for k in FILE_KEYS if getattr(self, k) is not None})
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        with open(tmp, "wb") as f:
            np.savez_compressed(f, **arrays, **extra)
        os.replace(tmp, path)
        return path

    @classmethod
    def load_npz(cls, path: str | Path) -> "Trajectory":
        """Read a trajectory written by `save_npz` (by `simulate`, `rig` or `track`).

        Raises:
            TrajectoryFileError: the file is missing, unreadable or lacks `t` and `q`.
        """
        try:
            with np.load(path) as f:
                missing = {"t", "q"} - set(f.files)
                if missing:
                    raise TrajectoryFileError(
                        f"{path}: not a trajectory file (missing {', '.join(sorted(missing))})")
                q = np.asarray(f["q"], np.float64)
                opt = {k: f[k] for k in FILE_KEYS if k in f.files}
                return cls(t=np.asarray(f["t"], np.float64), q=q,
                           qdot=f["qdot"] if "qdot" in f.files else np.full_like(q, np.nan),
                           complete=bool(f["complete"]) if "complete" in f.files else True,
                           **opt)
        except READ_ERRORS as e:
            if isinstance(e, TrajectoryFileError):
                raise
            hint = "" if isinstance(e, OSError) else ("; cut short? write it again with the "
                                                      "command that made it")
            raise TrajectoryFileError(f"{path}: cannot read a trajectory ({e}){hint}") from None


def backward_rates(t: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Backward-difference rates [n_t, ...] of q [n_t, ...] over times t [n_t] (NaN at k = 0)."""
    t, q = np.asarray(t, np.float64), np.asarray(q, np.float64)
    qdot = np.full_like(q, np.nan)
    if len(t) > 1:
        dt = np.diff(t).reshape((-1,) + (1,) * (q.ndim - 1))
        qdot[1:] = (q[1:] - q[:-1]) / dt
    return qdot


def to_absolute(q: np.ndarray, reference_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Displacements q [..., n, 3] -> absolute poses x, y (m), theta (rad), each [..., n], given
    the reference centroids [n, 2] in the sample frame (x right, y up)."""
    q = np.asarray(q, np.float64)
    ref = np.asarray(reference_m, np.float64)
    return ref[:, 0] + q[..., 0], ref[:, 1] + q[..., 1], q[..., 2]


def from_absolute(x, y, theta, reference_m: np.ndarray) -> np.ndarray:
    """Absolute poses x, y (m), theta (rad), each [..., n] -> displacements q [..., n, 3]."""
    ref = np.asarray(reference_m, np.float64)
    return np.stack([np.asarray(x, np.float64) - ref[:, 0], np.asarray(y, np.float64) - ref[:, 1],
                     np.asarray(theta, np.float64)], axis=-1)


def from_pose_messages(msgs, reference_m: np.ndarray, t0_ns: int | None = None) -> Trajectory:
    """`UnitPose2DArray` messages (one per frame, in time order; rclpy messages or decoded MCAP
    records alike: only their fields are read) -> `Trajectory` with t from `t0_ns` (default: the
    first stamp), rates by backward difference; units missing from a message count as lost.
    The way there: `ros_nodes.convert.unit_poses`."""
    ref = np.asarray(reference_m, np.float64)
    n, nt = ref.shape[0], len(msgs)
    if nt == 0:
        raise ValueError("no pose messages")
    t_ns = np.array([int(m.header.stamp.sec) * 1_000_000_000 + int(m.header.stamp.nanosec)
                     for m in msgs], np.int64)
    x = np.full((nt, n), np.nan)
    y, theta = x.copy(), x.copy()
    quality = np.full((nt, n), np.nan, np.float32)
    lost = np.ones((nt, n), bool)
    sigma = np.full((nt, n, 3), np.nan)
    has_sigma = False
    for k, m in enumerate(msgs):
        ids = np.asarray(m.ids, np.int64)
        if ids.size and (ids.min() < 0 or ids.max() >= n):
            raise ValueError(f"pose message {k}: unit id {int(ids.max())} outside 0..{n - 1}")
        x[k, ids], y[k, ids], theta[k, ids] = m.x, m.y, m.theta
        quality[k, ids], lost[k, ids] = m.quality, np.asarray(m.lost, bool)
        sx = getattr(m, "sigma_x", None)  # older recordings: no such field
        if sx is not None and len(sx) == ids.size and ids.size:
            sigma[k, ids] = np.stack([sx, m.sigma_y, m.sigma_theta], axis=-1)
            has_sigma = True
    q = from_absolute(x, y, theta, ref)
    q[lost] = np.nan
    t0 = t_ns[0] if t0_ns is None else int(t0_ns)
    return Trajectory.from_positions((t_ns - t0) * 1e-9, q, quality=quality, lost=lost,
                                     sigma=sigma if has_sigma else None)
