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
    image_size_px (optional [width, height]): size of the raw frames the calibration was made
        for; frames of another size are refused.
    camera_matrix (optional 3x3) and dist_coeffs (optional list of 4, 5, 8, 12 or 14): the
        lens (OpenCV's model, as `metarig camera-calibrate` writes them). With them, frames
        are undistorted before the homography, which then maps undistorted pixels (of the
        same camera matrix) to the rectified grid; both steps are one resampling, its maps
        built once per frame size. Other keys (reprojection errors, board) are ignored.

Pixel convention (as OpenCV): pixel (col, row) has its centre at integer coordinates, so a
sample point (x, y) m lies at col = origin_px[0] + x / m_per_px and
row = origin_px[1] - y / m_per_px when y_up (row = origin_px[1] + y / m_per_px otherwise).
"""

import math
from dataclasses import dataclass, field
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
        image_size_px: optional (width, height) of the raw frames it was made for.
        camera_matrix: optional [3, 3] lens intrinsics K, px (with `dist_coeffs`).
        dist_coeffs: optional OpenCV distortion coefficients (k1, k2, p1, p2[, k3, ...]).
    """

    fps: float
    m_per_px: float
    origin_px: tuple[float, float]
    y_up: bool = True
    homography: tuple[tuple[float, ...], ...] | None = None
    rectified_size_px: tuple[int, int] | None = None
    image_size_px: tuple[int, int] | None = None
    camera_matrix: tuple[tuple[float, ...], ...] | None = None
    dist_coeffs: tuple[float, ...] | None = None
    _maps: dict = field(default_factory=dict, init=False, repr=False, compare=False)

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
        if self.image_size_px is not None and (
            len(self.image_size_px) != 2 or min(self.image_size_px) < 1
        ):
            raise CalibrationError(
                f"image_size_px must be [width, height] > 0, got {self.image_size_px!r}"
            )
        if (self.camera_matrix is None) != (self.dist_coeffs is None):
            raise CalibrationError("camera_matrix and dist_coeffs come together (or neither)")
        if self.camera_matrix is not None:
            k = np.asarray(self.camera_matrix, dtype=np.float64)
            if k.shape != (3, 3) or not np.all(np.isfinite(k)) or k[0, 0] <= 0 or \
                    k[1, 1] <= 0 or not np.allclose(k[2], [0.0, 0.0, 1.0]) or k[1, 0] != 0:
                raise CalibrationError("camera_matrix must be [[fx, s, cx], [0, fy, cy], "
                                       "[0, 0, 1]] with fx, fy > 0")
            d = np.asarray(self.dist_coeffs, dtype=np.float64)
            if d.ndim != 1 or len(d) not in (4, 5, 8, 12, 14) or not np.all(np.isfinite(d)):
                raise CalibrationError("dist_coeffs must be 4, 5, 8, 12 or 14 numbers")

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

    def size_mismatch(self, shape: tuple[int, ...]) -> str:
        """Why a raw frame of `shape` (rows, cols, ...) does not fit ("" when it does)."""
        if self.image_size_px is None or tuple(shape[1::-1]) == tuple(self.image_size_px):
            return ""
        w, h = self.image_size_px
        return (f"frame is {shape[1]}x{shape[0]} px, the calibration was made for {w}x{h} px "
                "(another camera, binning or region of interest?)")

    def rectify(self, frame: np.ndarray) -> np.ndarray:
        """Warp a raw frame [h, w] onto the rectified grid (identity without a homography
        and lens); with a lens, undistortion and homography are one remap."""
        if self.camera_matrix is not None:
            key = frame.shape[:2]
            maps = self._maps.get(key)
            if maps is None:
                maps = self._maps[key] = self._lens_maps(frame.shape[1], frame.shape[0])
            return cv2.remap(frame, maps[0], maps[1], cv2.INTER_CUBIC,
                             borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        if self.homography is None:
            return frame
        h = np.asarray(self.homography, dtype=np.float64)
        w_out, h_out = self.rectified_size_px or (frame.shape[1], frame.shape[0])
        return cv2.warpPerspective(
            frame, h, (int(w_out), int(h_out)), flags=cv2.INTER_CUBIC,
            borderMode=cv2.BORDER_CONSTANT, borderValue=0,
        )

    def _lens_maps(self, w_in: int, h_in: int) -> tuple[np.ndarray, np.ndarray]:
        """Raw-pixel (col, row) float32 maps [h_out, w_out] of every rectified pixel: the
        homography's inverse to undistorted pixels, then the lens model forward."""
        k = np.asarray(self.camera_matrix, dtype=np.float64)
        d = np.asarray(self.dist_coeffs, dtype=np.float64)
        h = np.eye(3) if self.homography is None else np.asarray(self.homography, np.float64)
        w_out, h_out = self.rectified_size_px or (w_in, h_in)
        cc, rr = np.meshgrid(np.arange(w_out, dtype=np.float64),
                             np.arange(h_out, dtype=np.float64))
        grid = np.stack([cc, rr, np.ones_like(cc)], -1).reshape(-1, 3)
        und = grid @ (np.linalg.inv(k) @ np.linalg.inv(h)).T  # normalised camera rays
        # points beyond the plane's horizon come back with the other sign than the plane
        # point the optical axis meets (assumed seen: the camera looks at the sample)
        ahead = und[:, 2] * np.sign((h @ k @ [0.0, 0.0, 1.0])[2]) > 0
        xy = und[:, :2] / np.where(np.abs(und[:, 2:3]) > 1e-300, und[:, 2:3], 1e-300)
        # the distortion polynomial folds back beyond the frame: keep rays within 5 % of the
        # widest ray the raw frame sees, map the rest outside the frame
        corners = np.array([[0, 0], [w_in - 1, 0], [0, h_in - 1], [w_in - 1, h_in - 1]],
                           dtype=np.float64).reshape(-1, 1, 2)
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
        r_max = np.max(np.sum(cv2.undistortPoints(corners, k, d, criteria=crit) ** 2, -1))
        inside = ahead & (np.sum(xy**2, 1) <= 1.1 * r_max)
        pts = np.column_stack([np.where(inside[:, None], xy, 0.0), np.ones(len(xy))])
        raw, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), k, d)
        raw = raw.reshape(-1, 2)
        raw[~inside] = -10.0
        return (raw[:, 0].reshape(h_out, w_out).astype(np.float32),
                raw[:, 1].reshape(h_out, w_out).astype(np.float32))

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
        if self.image_size_px is not None:
            out["image_size_px"] = list(self.image_size_px)
        if self.camera_matrix is not None:
            out["camera_matrix"] = [list(r) for r in self.camera_matrix]
            out["dist_coeffs"] = list(self.dist_coeffs)
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
    optional = {}
    for key in ("rectified_size_px", "image_size_px"):
        v = d.get(key)
        if v is None:
            continue
        try:
            optional[key] = (int(v[0]), int(v[1]))
        except (TypeError, ValueError, IndexError, KeyError) as exc:
            raise CalibrationError(f"{where}: {key!r} must be [width, height]") from exc
    for key in ("camera_matrix", "dist_coeffs"):
        if d.get(key) is None:
            continue
        try:
            a = np.asarray(d[key], dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise CalibrationError(f"{where}: {key!r} must be numbers") from exc
        optional[key] = tuple(map(tuple, a.tolist())) if a.ndim == 2 else tuple(a.ravel().tolist())
    try:
        return Calibration(
            fps=_number(d, "fps", where),
            m_per_px=_number(d, "m_per_px", where),
            origin_px=(float(origin[0]), float(origin[1])),
            y_up=y_up,
            homography=hom,
            **optional,
        )
    except CalibrationError as exc:
        if str(exc).startswith(where):
            raise
        raise CalibrationError(f"{where}: {exc}") from None


def load_calibration(path: str | Path) -> Calibration:
    """Read a calibration JSON file; raises `CalibrationError` naming the file on any problem."""
    d = read_json(path, CalibrationError, "calibration")
    return calibration_from_dict(d, where=str(path))
