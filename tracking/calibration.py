"""Camera calibration for tracking: load and validate the JSON, map sample frame <-> pixels.

Calibration JSON keys:
    fps (float, > 0): frame rate; frame k is at t = k / fps seconds.
    m_per_px (float, > 0): metres per pixel of the square-on (rectified) image.
    origin_px ([col, row]): pixel position of the sample-frame origin.
    y_up (bool): the sample y axis points up the image (rows grow downwards).
    homography (optional 3x3 list): maps raw camera pixels (col, row, 1) to the rectified
        pixel grid in which m_per_px / origin_px / y_up hold (e.g. `cv2.findHomography` from
        image points to their square-on positions). Frames are rectified with it first.
    rectified_size_px (optional [width, height]): size of the rectified image; defaults to
        the raw frame size.

Pixel convention (as OpenCV): pixel (col, row) has its centre at integer coordinates, so a
sample point (x, y) m lies at col = origin_px[0] + x / m_per_px and
row = origin_px[1] - y / m_per_px when y_up (row = origin_px[1] + y / m_per_px otherwise).
"""

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from tracking.jsonfile import read_json


class CalibrationError(ValueError):
    """A calibration file or value is missing or invalid (message names the problem)."""


@dataclass(frozen=True, slots=True)
class Calibration:
    """Camera calibration (see module docstring for the meaning of each field).

    Attributes:
        fps: frames per second, 1/s.
        m_per_px: metres per rectified pixel.
        origin_px: (col, row) of the sample-frame origin in rectified pixels.
        y_up: sample y points up the image.
        homography: optional [3, 3] raw pixel -> rectified pixel map.
        rectified_size_px: optional (width, height) of the rectified image.
    """

    fps: float
    m_per_px: float
    origin_px: tuple[float, float]
    y_up: bool = True
    homography: tuple[tuple[float, ...], ...] | None = None
    rectified_size_px: tuple[int, int] | None = None

    def __post_init__(self):
        if not (math.isfinite(self.fps) and self.fps > 0):
            raise CalibrationError(f"fps must be a positive number, got {self.fps!r}")
        if not (math.isfinite(self.m_per_px) and self.m_per_px > 0):
            raise CalibrationError(f"m_per_px must be a positive number, got {self.m_per_px!r}")
        if len(self.origin_px) != 2 or not all(math.isfinite(v) for v in self.origin_px):
            raise CalibrationError(f"origin_px must be [col, row], got {self.origin_px!r}")
        if self.homography is not None:
            h = np.asarray(self.homography, dtype=np.float64)
            if h.shape != (3, 3) or not np.all(np.isfinite(h)) or abs(np.linalg.det(h)) < 1e-12:
                raise CalibrationError("homography must be an invertible 3x3 matrix of numbers")
        if self.rectified_size_px is not None and (
            len(self.rectified_size_px) != 2 or min(self.rectified_size_px) < 1
        ):
            raise CalibrationError(
                f"rectified_size_px must be [width, height] > 0, got {self.rectified_size_px!r}"
            )

    def sample_to_px(self, xy_m: np.ndarray) -> np.ndarray:
        """Sample-frame points [..., 2] (m) -> rectified pixel (col, row) [..., 2]."""
        xy = np.asarray(xy_m, dtype=np.float64)
        sy = -1.0 if self.y_up else 1.0
        return np.stack(
            [
                self.origin_px[0] + xy[..., 0] / self.m_per_px,
                self.origin_px[1] + sy * xy[..., 1] / self.m_per_px,
            ],
            axis=-1,
        )

    def px_to_sample(self, px: np.ndarray) -> np.ndarray:
        """Rectified pixel (col, row) [..., 2] -> sample-frame points [..., 2] (m)."""
        p = np.asarray(px, dtype=np.float64)
        sy = -1.0 if self.y_up else 1.0
        return np.stack(
            [
                (p[..., 0] - self.origin_px[0]) * self.m_per_px,
                sy * (p[..., 1] - self.origin_px[1]) * self.m_per_px,
            ],
            axis=-1,
        )

    @property
    def image_rotation_sign(self) -> float:
        """Sign turning a rotation in (col, row) image axes into a CCW sample rotation."""
        return -1.0 if self.y_up else 1.0

    def rectify(self, frame: np.ndarray) -> np.ndarray:
        """Warp a raw frame [h, w] onto the rectified grid (identity without a homography)."""
        if self.homography is None:
            return frame
        h = np.asarray(self.homography, dtype=np.float64)
        w_out, h_out = self.rectified_size_px or (frame.shape[1], frame.shape[0])
        return cv2.warpPerspective(
            frame, h, (int(w_out), int(h_out)), flags=cv2.INTER_CUBIC,
            borderMode=cv2.BORDER_CONSTANT, borderValue=0,
        )

    def to_json(self) -> dict:
        """The calibration as a JSON-ready dict (inverse of `calibration_from_dict`)."""
        out: dict = {
            "fps": self.fps,
            "m_per_px": self.m_per_px,
            "origin_px": list(self.origin_px),
            "y_up": self.y_up,
        }
        if self.homography is not None:
            out["homography"] = [list(r) for r in self.homography]
        if self.rectified_size_px is not None:
            out["rectified_size_px"] = list(self.rectified_size_px)
        return out


def _number(d: dict, key: str, where: str) -> float:
    if key not in d:
        raise CalibrationError(f"{where}: missing key {key!r}")
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise CalibrationError(f"{where}: {key!r} must be a number, got {v!r}")
    return float(v)


def calibration_from_dict(d: dict, where: str = "calibration") -> Calibration:
    """Build and validate a `Calibration` from a parsed JSON object."""
    if not isinstance(d, dict):
        raise CalibrationError(f"{where}: expected a JSON object")
    origin = d.get("origin_px")
    if (
        not isinstance(origin, (list, tuple))
        or len(origin) != 2
        or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in origin)
    ):
        raise CalibrationError(f"{where}: 'origin_px' must be [col, row] numbers, got {origin!r}")
    y_up = d.get("y_up")
    if not isinstance(y_up, bool):
        raise CalibrationError(f"{where}: 'y_up' must be true or false, got {y_up!r}")
    hom = d.get("homography")
    if hom is not None:
        try:
            hom = tuple(tuple(float(v) for v in row) for row in hom)
        except (TypeError, ValueError) as exc:
            raise CalibrationError(f"{where}: 'homography' must be a 3x3 list of numbers") from exc
    size = d.get("rectified_size_px")
    if size is not None:
        try:
            size = (int(size[0]), int(size[1]))
        except (TypeError, ValueError, IndexError) as exc:
            raise CalibrationError(f"{where}: 'rectified_size_px' must be [width, height]") from exc
    try:
        return Calibration(
            fps=_number(d, "fps", where),
            m_per_px=_number(d, "m_per_px", where),
            origin_px=(float(origin[0]), float(origin[1])),
            y_up=y_up,
            homography=hom,
            rectified_size_px=size,
        )
    except CalibrationError as exc:
        if str(exc).startswith(where):
            raise
        raise CalibrationError(f"{where}: {exc}") from None


def load_calibration(path: str | Path) -> Calibration:
    """Read a calibration JSON file; raises `CalibrationError` naming the file on any problem."""
    d = read_json(path, CalibrationError, "calibration")
    return calibration_from_dict(d, where=str(path))
