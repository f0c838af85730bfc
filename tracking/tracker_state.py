"""The DIC tracking problem and its memory: outlines and calibration (`DICTracker`), the
state carried from frame to frame (`TrackerState`), one frame's result (`FramePoses`), and the
frame preparation and reference subsets every frame starts from (pure, no ROS).

Poses: the reference configuration is the outline given (frame `reference` shows it). q =
(u, v, theta): displacement of each unit's area centroid in the sample frame (m) and its
counter-clockwise rotation about it (rad). Internally poses live in rectified pixel axes:
alpha (col towards row) and t (px); see `Calibration` for the maps.
"""

import logging
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from metarig.polygon import area_centroids
from tracking.calibration import Calibration
from tracking.checks import Pieces, split_refs
from tracking.dic_config import DICConfig
from tracking.kernels import bspline_coefficients
from tracking.reference import RefSet, build_refs
from tracking.units import validate_polygons

log = logging.getLogger(__name__)


class FrameError(ValueError):
    """A frame cannot be tracked (wrong size, blank, non-finite); its units are flagged lost."""


@dataclass(frozen=True, slots=True)
class DICTracker:
    """Static tracking problem: outlines, calibration, settings.

    Attributes:
        polygons_m: [n, nv, 2] reference outlines, sample frame, m.
        calib: camera calibration.
        cfg: tracker settings.
        bonds: [nb, 4] int ligaments (unit a, vertex k, unit b, vertex l) for the check
            against the neighbours (`tracking.units.bonds_from_outlines`), None: no check.
        polys_px: [n, nv, 2] reference outlines in rectified pixels.
        centroid_px: [n, 2] area centroids in rectified pixels.
    """

    polygons_m: np.ndarray
    calib: Calibration
    cfg: DICConfig = field(default_factory=DICConfig)
    bonds: np.ndarray | None = None
    polys_px: np.ndarray = field(init=False)
    centroid_px: np.ndarray = field(init=False)

    def __post_init__(self):
        polys = validate_polygons(self.polygons_m)
        object.__setattr__(self, "polygons_m", polys)
        if self.bonds is not None:
            b = np.asarray(self.bonds, np.int64).reshape(-1, 4)
            n, nv = polys.shape[:2]
            if np.any(b < 0) or np.any(b[:, [0, 2]] >= n) or np.any(b[:, [1, 3]] >= nv) \
                    or np.any(b[:, 0] == b[:, 2]):
                raise ValueError("bonds must join vertices (< n_vertices) of two distinct "
                                 "units (< n_units)")
            object.__setattr__(self, "bonds", b)
        object.__setattr__(self, "polys_px", self.calib.sample_to_px(polys))
        object.__setattr__(self, "centroid_px", self.calib.sample_to_px(area_centroids(polys)))

    @property
    def n_units(self) -> int:
        return int(self.polygons_m.shape[0])


@dataclass(frozen=True, slots=True)
class TrackerState:
    """Tracker memory between frames (rectified pixel axes).

    Attributes:
        refs: reference subsets of every unit.
        ref_alpha: [n] rotation of each reference from the outline, rad.
        ref_t: [n, 2] centroid displacement of each reference from the outline, px.
        alpha, t: [n], [n, 2] last good pose of each unit.
        prev_alpha, prev_t: pose one frame before that (NaN: unknown), for the prediction.
        lost: [n] the unit is currently lost.
        shape: (rows, cols) of the rectified frames.
        acquired: the first frame was registered against the reference (`acquire_frame`).
        refs0: the reference image's own subsets (poses are from them; refreshed references
            are checked against them every frame), None to skip that check.
        pieces, pieces0: the subsets of `refs` and `refs0` cut into pieces for the check of
            every pose (`DICConfig.check_pieces`), None without it.
        refs_own: `refs` and `pieces` are this state's own arrays (no longer those of
            `refs0`), so a reference update writes them in place. `track_frame` therefore
            consumes the state it is given: keep only the state it returns.
    """

    refs: RefSet
    ref_alpha: np.ndarray
    ref_t: np.ndarray
    alpha: np.ndarray
    t: np.ndarray
    prev_alpha: np.ndarray
    prev_t: np.ndarray
    lost: np.ndarray
    shape: tuple[int, int]
    acquired: bool = False
    refs0: RefSet | None = None
    pieces: Pieces | None = None
    pieces0: Pieces | None = None
    refs_own: bool = False


@dataclass(frozen=True, slots=True)
class FramePoses:
    """Tracking result of one frame.

    Attributes:
        q: [n, 3] (u m, v m, theta rad) from the reference outline; NaN where lost.
        quality: [n] ZNCC of the registration in [-1, 1] (NaN when not measurable).
        lost: [n] the unit is lost in this frame.
        error: why the whole frame was unusable ("" when it was tracked).
        sigma: [n, 3] standard error of q (m, m, rad; `pose_sigma`), NaN where lost.
    """

    q: np.ndarray
    quality: np.ndarray
    lost: np.ndarray
    error: str = ""
    sigma: np.ndarray | None = None


@dataclass(frozen=True, slots=True)
class PreparedFrame:
    """A frame ready for tracking: float32 pixels and their B-spline coefficients [h, w]."""

    img: np.ndarray
    coef: np.ndarray


def prepare_frame(tracker: DICTracker, frame: np.ndarray) -> PreparedFrame:
    """Rectify, convert to grey float32, smooth and spline-filter a raw frame.

    Raises:
        FrameError: the frame is empty, not an image, non-finite or blank (uniform).
    """
    a = np.asarray(frame)
    if a.ndim == 3 and a.shape[2] in (3, 4):
        a = cv2.cvtColor(a, cv2.COLOR_BGR2GRAY if a.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
    if a.ndim != 2 or a.size == 0:
        raise FrameError(f"frame has shape {a.shape}, expected a 2-D grey image")
    if why := tracker.calib.size_mismatch(a.shape):
        raise FrameError(why)
    img = tracker.calib.rectify(a.astype(np.float32, copy=False))
    if not np.all(np.isfinite(img)):
        raise FrameError("frame has non-finite pixels")
    if float(img.max()) - float(img.min()) <= 0.0:
        raise FrameError("frame is blank (uniform)")
    s = tracker.cfg.prefilter_sigma_px
    if s > 0:
        img = cv2.GaussianBlur(img, (0, 0), s, borderType=cv2.BORDER_REFLECT)
    return PreparedFrame(img=np.ascontiguousarray(img), coef=bspline_coefficients(img))


def rot(alpha: np.ndarray) -> np.ndarray:
    """Rotation matrices [..., 2, 2] of the angles alpha [...] (rad, col towards row)."""
    c, s = np.cos(alpha), np.sin(alpha)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def posed_outlines(tracker: DICTracker, idx, alpha, t) -> tuple[np.ndarray, np.ndarray]:
    """Outlines [k, nv, 2] and centroids [k, 2] (px) of units idx at poses (alpha, t)."""
    c = tracker.centroid_px[idx]
    rel = tracker.polys_px[idx] - c[:, None, :]
    polys = np.einsum("kij,kvj->kvi", rot(alpha), rel) + (c + t)[:, None, :]
    return polys, c + t


def init_state(tracker: DICTracker, reference: np.ndarray) -> TrackerState:
    """Build every unit's reference subset from a frame showing the reference configuration.

    Raises:
        FrameError: the reference frame is unusable.
    """
    prep = prepare_frame(tracker, reference)
    n = tracker.n_units
    refs = build_refs(
        prep.img,
        prep.coef,
        tracker.polys_px,
        tracker.centroid_px,
        tracker.cfg.margin_px,
        tracker.cfg.min_points,
    )
    unusable = refs.count == 0
    if unusable.any():
        log.warning(
            "%d of %d units cannot be tracked (outside the frame or too small): %s",
            int(unusable.sum()),
            n,
            np.flatnonzero(unusable)[:20].tolist(),
        )
    nan2 = np.full((n, 2), np.nan)
    parts = tracker.cfg.check_pieces
    pieces = split_refs(refs, parts) if parts else None
    return TrackerState(
        refs=refs,
        ref_alpha=np.zeros(n),
        ref_t=np.zeros((n, 2)),
        alpha=np.zeros(n),
        t=np.zeros((n, 2)),
        prev_alpha=np.full(n, np.nan),
        prev_t=nan2,
        lost=unusable,
        shape=prep.img.shape,
        refs0=refs,
        pieces=pieces,
        pieces0=pieces,
    )


def to_sample(tracker: DICTracker, alpha: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Pixel-axis poses -> q [k, 3] (u m, v m, theta rad)."""
    cal = tracker.calib
    sy = -1.0 if cal.y_up else 1.0
    return np.stack(
        [t[:, 0] * cal.m_per_px, sy * t[:, 1] * cal.m_per_px, cal.image_rotation_sign * alpha],
        axis=-1,
    )


def all_lost(state: TrackerState, reason: str) -> tuple[TrackerState, FramePoses]:
    """Flag every unit lost for a frame that could not be used (keeps the last poses)."""
    n = state.lost.size
    st = replace(
        state, lost=np.ones(n, bool), prev_alpha=np.full(n, np.nan), prev_t=np.full((n, 2), np.nan)
    )
    return st, FramePoses(
        np.full((n, 3), np.nan),
        np.full(n, np.nan),
        np.ones(n, bool),
        reason or "unusable frame",
        np.full((n, 3), np.nan),
    )
