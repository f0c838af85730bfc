"""DIC tracker: sub-pixel rigid pose of every unit in every frame (pure logic, no ROS).

Per frame: predict each unit's pose (constant velocity), register it by rigid IC-GN with
ZNSSD against the unit's reference subset, re-acquire units whose correlation dropped by a
template search around the prediction, flag as lost (pose NaN, never guessed) those still
poor or whose subset leaves the frame, and refresh the reference of the units that need it
(rotated far from their reference, or correlation degraded). All units are solved in one
compiled batch; the offline CLI and the live node call the same `track_frame`.

The first frame tracked is found, not assumed: every unit is searched for over offsets and
rotations around its reference position (`acquire_frame`), so the reference image may show the
sample unloaded and the first frame pre-compressed (the rig's procedure); slender units too small
for a search template start from their neighbours' motion.

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
from tracking.checks import Pieces, piece_deviation, rigid_fit, split_refs
from tracking.icgn import icgn
from tracking.kernels import bspline_coefficients
from tracking.reference import RefSet, build_refs, replace_refs
from tracking.search import MIN_TEMPLATE_HALF, acquire, coarse_search
from tracking.units import validate_polygons

log = logging.getLogger(__name__)


class FrameError(ValueError):
    """A frame cannot be tracked (wrong size, blank, non-finite); its units are flagged lost."""


@dataclass(frozen=True, slots=True)
class DICConfig:
    """Tracker settings.

    Attributes:
        margin_px: subset points keep this distance from the unit outline, px.
        min_points: units with fewer subset points are never tracked (always lost).
        max_iter: IC-GN iteration cap per frame.
        tol_px: IC-GN convergence: estimated remaining error of any subset point, px.
        max_move_px: IC-GN gives up when the pose wanders this far from its start, px.
        zncc_lost: a tracked unit whose ZNCC stays below this is declared lost.
        zncc_reacquire: below this, a coarse search is tried; a lost unit must reach it again.
        zncc_update: a unit tracked below this gets a new reference.
        max_ref_rotation: a unit rotated more than this from its reference gets a new one, rad.
        search_radius_px: half-width of the re-acquisition window around the prediction, px.
        lost_search_radius_px: the same for units already lost (around their last pose), px.
        prefilter_sigma_px: Gaussian smoothing of every frame before tracking, px (0: none).
        predict: warm-start from a constant-velocity prediction (else the last pose).
        acquire_radius_px: half-width of the first frame's search for every unit around its
            reference position, px (0: a tenth of the sample's height in the image, which
            covers any pre-compression the rig allows, 9 %, even from one stage alone).
        acquire_max_rotation, acquire_rotation_step: trial rotations of that search, rad.
        acquire_neighbours: units without a usable search template (slender ones) start from
            the rigid motion of this many nearest units found by the search.
        verify_px, verify_rad: a pose registered against a refreshed reference must agree this
            well (largest subset-point shift, px; rotation, rad) with the reference image's own
            subset where that registers poorly, else the unit is lost (`track_frame`).
        check_pieces: every pose is checked by cutting its unit's subset into this many pieces
            along its long axis and registering each on its own (`tracking.checks`); 0: no check.
        check_sigmas, check_floor_px, check_max_px: a piece whose centroid lands further
            from where the unit's pose puts it than check_sigmas of its standard error (at
            the unit's correlation), bounded to [check_floor_px, check_max_px], fails the pose:
            the unit is searched again from its pieces' motion, and lost if that fails too.
            The upper bound keeps a poor fit from excusing itself: a wrong pose correlates
            worse, which widens every standard error; 0.25 px at a piece is ~30 mrad on a
            sliver whose pieces lie 9 px from its centre. A piece too small for it (check_sigmas
            of its standard error at a near-perfect fit beyond it) is bounded by that instead.
        sigma_floor_px: systematic error of every subset point's registered position that
            noise does not explain (interpolation), px: added to each pose's standard error in
            quadrature (`pose_sigma`).
        sigma_blur_share: motion blur that the warp does not model: each pose's systematic
            floor grows by this share of the unit's motion since the previous frame (px).
            Both defaults are measured on the simulated rig's footage (exposure half a frame,
            `SIGMA_BLUR_SHARE`); on a real camera, measure them with rigid-motion tests (0 for
            the blur share where the exposure is short).
    """

    margin_px: float = 2.5
    min_points: int = 50
    max_iter: int = 20
    tol_px: float = 2e-3
    max_move_px: float = 8.0
    zncc_lost: float = 0.8
    zncc_reacquire: float = 0.9
    zncc_update: float = 0.9
    max_ref_rotation: float = 0.2
    search_radius_px: int = 12
    lost_search_radius_px: int = 24
    prefilter_sigma_px: float = 0.8
    predict: bool = True
    acquire_radius_px: int = 0
    acquire_max_rotation: float = 0.7
    acquire_rotation_step: float = 0.05
    acquire_neighbours: int = 4
    verify_px: float = 0.5
    verify_rad: float = 0.01
    check_pieces: int = 2
    check_sigmas: float = 5.0
    check_floor_px: float = 0.1
    check_max_px: float = 0.25
    sigma_floor_px: float = 0.005
    sigma_blur_share: float = 0.006

    def __post_init__(self):
        if not (0.0 <= self.zncc_lost <= self.zncc_reacquire <= 1.0):
            raise ValueError("need 0 <= zncc_lost <= zncc_reacquire <= 1")
        if self.margin_px < 0 or self.max_iter < 1 or self.tol_px <= 0:
            raise ValueError("margin_px >= 0, max_iter >= 1 and tol_px > 0 are required")
        if self.check_pieces == 1 or self.check_pieces < 0:
            raise ValueError(f"check_pieces must be 0 (no check) or >= 2, got "
                             f"{self.check_pieces}")


@dataclass(frozen=True, slots=True)
class DICTracker:
    """Static tracking problem: outlines, calibration, settings.

    Attributes:
        polygons_m: [n, nv, 2] reference outlines, sample frame, m.
        calib: camera calibration.
        cfg: tracker settings.
        polys_px: [n, nv, 2] reference outlines in rectified pixels.
        centroid_px: [n, 2] area centroids in rectified pixels.
    """

    polygons_m: np.ndarray
    calib: Calibration
    cfg: DICConfig = field(default_factory=DICConfig)
    polys_px: np.ndarray = field(init=False)
    centroid_px: np.ndarray = field(init=False)

    def __post_init__(self):
        polys = validate_polygons(self.polygons_m)
        object.__setattr__(self, "polygons_m", polys)
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


def _rot(alpha: np.ndarray) -> np.ndarray:
    c, s = np.cos(alpha), np.sin(alpha)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def _posed_outlines(tracker: DICTracker, idx, alpha, t) -> tuple[np.ndarray, np.ndarray]:
    """Outlines [k, nv, 2] and centroids [k, 2] (px) of units idx at poses (alpha, t)."""
    c = tracker.centroid_px[idx]
    rel = tracker.polys_px[idx] - c[:, None, :]
    polys = np.einsum("kij,kvj->kvi", _rot(alpha), rel) + (c + t)[:, None, :]
    return polys, c + t


def init_state(tracker: DICTracker, reference: np.ndarray) -> TrackerState:
    """Build every unit's reference subset from a frame showing the reference configuration.

    Raises:
        FrameError: the reference frame is unusable.
    """
    prep = prepare_frame(tracker, reference)
    n = tracker.n_units
    refs = build_refs(prep.img, prep.coef, tracker.polys_px, tracker.centroid_px,
                      tracker.cfg.margin_px, tracker.cfg.min_points)
    unusable = refs.count == 0
    if unusable.any():
        log.warning("%d of %d units cannot be tracked (outside the frame or too small): %s",
                    int(unusable.sum()), n, np.flatnonzero(unusable)[:20].tolist())
    nan2 = np.full((n, 2), np.nan)
    parts = tracker.cfg.check_pieces
    pieces = split_refs(refs, parts) if parts else None
    return TrackerState(
        refs=refs, ref_alpha=np.zeros(n), ref_t=np.zeros((n, 2)), alpha=np.zeros(n),
        t=np.zeros((n, 2)), prev_alpha=np.full(n, np.nan), prev_t=nan2, lost=unusable,
        shape=prep.img.shape, refs0=refs, pieces=pieces, pieces0=pieces,
    )


def _to_sample(tracker: DICTracker, alpha: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Pixel-axis poses -> q [k, 3] (u m, v m, theta rad)."""
    cal = tracker.calib
    sy = -1.0 if cal.y_up else 1.0
    return np.stack([t[:, 0] * cal.m_per_px, sy * t[:, 1] * cal.m_per_px,
                     cal.image_rotation_sign * alpha], axis=-1)


def all_lost(state: TrackerState, reason: str) -> tuple[TrackerState, FramePoses]:
    """Flag every unit lost for a frame that could not be used (keeps the last poses)."""
    n = state.lost.size
    st = replace(state, lost=np.ones(n, bool), prev_alpha=np.full(n, np.nan),
                 prev_t=np.full((n, 2), np.nan))
    return st, FramePoses(np.full((n, 3), np.nan), np.full(n, np.nan), np.ones(n, bool),
                          reason or "unusable frame", np.full((n, 3), np.nan))


def track_frame(
    tracker: DICTracker, state: TrackerState, frame: np.ndarray | PreparedFrame
) -> tuple[TrackerState, FramePoses]:
    """Track all units in one frame.

    Args:
        tracker: the static problem.
        state: memory from the previous frame (or `init_state`).
        frame: raw [h, w] frame (any grey dtype) or an already prepared one.

    Returns:
        The new state and this frame's poses. A frame that cannot be used (blank, wrong
        size, non-finite) flags every unit lost instead of raising (`FramePoses.error` says
        why).
    """
    cfg = tracker.cfg
    try:
        prep = frame if isinstance(frame, PreparedFrame) else prepare_frame(tracker, frame)
        if prep.img.shape != state.shape:
            raise FrameError(f"frame size {prep.img.shape} differs from the reference "
                             f"{state.shape}")
    except FrameError as exc:
        log.debug("frame skipped, all units flagged lost: %s", exc)
        return all_lost(state, str(exc))
    if not state.acquired:
        state = acquire_frame(tracker, state, prep)
    refs = state.refs
    n = tracker.n_units
    usable = refs.count > 0
    # constant-velocity prediction (global pixel-axis poses)
    have_prev = np.isfinite(state.prev_alpha) & ~state.lost & cfg.predict
    pa = np.where(have_prev, 2.0 * state.alpha - np.nan_to_num(state.prev_alpha), state.alpha)
    pt = np.where(have_prev[:, None], 2.0 * state.t - np.nan_to_num(state.prev_t), state.t)
    a0, w0 = pa - state.ref_alpha, pt - state.ref_t  # relative to each unit's reference

    alpha, w = np.full(n, np.nan), np.full((n, 2), np.nan)
    zncc, ok = np.full(n, np.nan), np.zeros(n, bool)
    inside = np.zeros(n, bool)
    tracked = np.flatnonzero(usable & ~state.lost)
    if tracked.size:
        r = icgn(prep.coef, refs, tracked, a0[tracked], w0[tracked], cfg.max_iter, cfg.tol_px,
                 cfg.max_move_px)
        alpha[tracked], w[tracked], zncc[tracked] = r.alpha, r.w, r.zncc
        inside[tracked] = r.inside
        ok[tracked] = r.inside & (r.zncc >= cfg.zncc_reacquire)
    # re-acquire: tracked units that came out poor (but still in the frame) and lost units
    retry_tracked = tracked[~ok[tracked] & inside[tracked]]
    retry_lost = np.flatnonzero(usable & state.lost)
    for retry, radius, accept in (
        (retry_tracked, cfg.search_radius_px, cfg.zncc_lost),
        (retry_lost, cfg.lost_search_radius_px, cfg.zncc_reacquire),
    ):
        if retry.size == 0:
            continue
        ws, score = coarse_search(prep.img, refs, retry, a0[retry], w0[retry], radius)
        found = np.isfinite(score)
        cand = retry[found]
        if cand.size:
            r = icgn(prep.coef, refs, cand, a0[cand], ws[found], cfg.max_iter, cfg.tol_px,
                     cfg.max_move_px)
            better = r.inside & (r.zncc > np.nan_to_num(zncc[cand], nan=-np.inf))
            sel = cand[better]
            alpha[sel], w[sel], zncc[sel] = r.alpha[better], r.w[better], r.zncc[better]
            inside[sel] = True
        ok[retry] = inside[retry] & (zncc[retry] >= accept)
    ok &= np.isfinite(alpha) & np.all(np.isfinite(w), axis=1)
    # units too slender for a search template: from their tracked neighbours' motion
    slim = np.union1d(retry_tracked, retry_lost)
    slim = slim[(refs.tpl_half[slim] < MIN_TEMPLATE_HALF) & ~ok[slim]]
    anchors = np.flatnonzero(ok)
    if slim.size and anchors.size:
        a_abs = state.ref_alpha + np.nan_to_num(alpha)
        t_abs = state.ref_t + np.nan_to_num(w)
        a, tt, zn = _from_neighbours(tracker, refs, prep, slim, anchors, a_abs, t_abs,
                                     state.ref_alpha, state.ref_t)
        got = zn >= cfg.zncc_reacquire
        sel = slim[got]
        alpha[sel], w[sel] = a[got] - state.ref_alpha[sel], tt[got] - state.ref_t[sel]
        zncc[sel], ok[sel] = zn[got], True

    # new poses: good units move on, the others keep their last good pose and are lost
    new_alpha = np.where(ok, state.ref_alpha + np.nan_to_num(alpha), state.alpha)
    new_t = np.where(ok[:, None], state.ref_t + np.nan_to_num(w), state.t)
    src_zncc, checked = zncc, np.zeros(n, bool)
    if state.refs0 is not None:
        ok, new_alpha, new_t, src_zncc, checked = _verify_against_reference(
            tracker, state, prep, ok, new_alpha, new_t, zncc)
    if state.pieces is not None:
        ok, new_alpha, new_t, src_zncc = _check_by_pieces(tracker, state, prep, ok, checked,
                                                          new_alpha, new_t, src_zncc)
    src_refs = [(refs, ok & ~checked, src_zncc), (state.refs0, ok & checked, src_zncc)]
    prev_alpha = np.where(ok & ~state.lost, state.alpha, np.nan)
    prev_t = np.where((ok & ~state.lost)[:, None], state.t, np.nan)
    # motion since the previous frame (px at the subset's edge; 0 where unknown): blur's scale
    moved = np.nan_to_num(np.hypot(*(new_t - prev_t).T)
                          + np.abs(new_alpha - prev_alpha) * refs.rmax)
    state = replace(state, alpha=new_alpha, t=new_t, prev_alpha=prev_alpha, prev_t=prev_t,
                    lost=~ok)
    state = _update_references(tracker, state, prep, ok, new_alpha - state.ref_alpha, src_zncc)

    q = np.full((n, 3), np.nan)
    q[ok] = _to_sample(tracker, new_alpha[ok], new_t[ok])
    sigma = np.full((n, 3), np.nan)
    cal = tracker.calib
    for rs, sel, zn in src_refs:
        if sel.any():
            floor = np.hypot(cfg.sigma_floor_px, cfg.sigma_blur_share * moved[sel])
            sigma[sel] = pose_sigma(rs, np.flatnonzero(sel), zn[sel], cfg.prefilter_sigma_px,
                                    floor) * np.array([cal.m_per_px, cal.m_per_px, 1.0])
    return state, FramePoses(q=q, quality=src_zncc, lost=~ok, sigma=sigma)


def _verify_against_reference(tracker: DICTracker, state: TrackerState, prep: PreparedFrame,
                              ok: np.ndarray, alpha: np.ndarray, t: np.ndarray,
                              zncc: np.ndarray):
    """Check the poses registered against a refreshed reference with the reference image's own
    subsets (drift-free: a refreshed reference taken at a slightly wrong pose carries that error
    into every later frame, at a high correlation). Where the original subset registers well
    from the pose found, its pose is the one reported; where it registers poorly but agrees
    within `DICConfig.verify_px` / `verify_rad`, the pose stands; otherwise the unit is lost.

    Returns (ok, alpha, t, zncc, checked): the verified flags, poses and correlations, and which
    units the original reference now vouches for."""
    cfg = tracker.cfg
    refreshed = ok & ((state.ref_alpha != 0.0) | np.any(state.ref_t != 0.0, axis=1))
    checked = np.zeros_like(ok)
    if not refreshed.any():
        return ok, alpha, t, zncc, checked
    idx = np.flatnonzero(refreshed)
    r = icgn(prep.coef, state.refs0, idx, alpha[idx], t[idx], cfg.max_iter, cfg.tol_px,
             cfg.max_move_px)
    z0 = np.nan_to_num(r.zncc, nan=-1.0)
    good = r.inside & r.converged & (z0 >= cfg.zncc_reacquire)
    rmax = state.refs0.rmax[idx]
    agree = (np.abs(r.alpha - alpha[idx]) <= cfg.verify_rad) \
        & (np.hypot(*(r.w - t[idx]).T) + rmax * np.abs(r.alpha - alpha[idx]) <= cfg.verify_px)
    fair = r.inside & (z0 >= cfg.zncc_lost) & agree
    ok, alpha, t, zncc = ok.copy(), alpha.copy(), t.copy(), zncc.copy()
    take = idx[good]
    alpha[take], t[take], zncc[take] = r.alpha[good], r.w[good], r.zncc[good]
    checked[take] = True
    bad = idx[~good & ~fair]
    if bad.size:
        log.debug("%d poses disagree with the reference image: flagged lost", bad.size)
    ok[bad] = False
    return ok, alpha, t, zncc, checked


def _check_by_pieces(tracker: DICTracker, state: TrackerState, prep: PreparedFrame,
                     ok: np.ndarray, checked: np.ndarray, alpha: np.ndarray, t: np.ndarray,
                     zncc: np.ndarray):
    """Check every good pose with its unit's pieces (`tracking.checks`), each against the
    reference it was registered with (the reference image's where `checked`). A unit whose
    pieces disagree is registered again from their own rigid motion; if its pieces disagree
    with that too, or it correlates below `zncc_lost`, it is lost.

    Returns (ok, alpha, t, zncc): the flags, poses (from the reference image, px, rad) and
    correlations after the check."""
    cfg = tracker.cfg
    ok, alpha, t, zncc = ok.copy(), alpha.copy(), t.copy(), zncc.copy()
    zero_a, zero_t = np.zeros_like(state.ref_alpha), np.zeros_like(state.ref_t)
    for refs, pieces, ra, rt, sel in (
        (state.refs, state.pieces, state.ref_alpha, state.ref_t, ok & ~checked),
        (state.refs0, state.pieces0, zero_a, zero_t, ok & checked),
    ):
        idx = np.flatnonzero(sel)
        if idx.size == 0:
            continue
        a_rel, w_rel = alpha[idx] - ra[idx], t[idx] - rt[idx]
        check = _pieces_agree(tracker, prep, pieces, idx, a_rel, w_rel, zncc[idx])
        bad = ~check[0]
        if not bad.any():
            continue
        redo = idx[bad]
        a0, w0 = rigid_fit(pieces.offset[pieces.index(redo)], check[1][bad])
        r = icgn(prep.coef, refs, redo, a0, w0, cfg.max_iter, cfg.tol_px, cfg.max_move_px)
        good = r.inside & (np.nan_to_num(r.zncc, nan=-1.0) >= cfg.zncc_lost)
        if good.any():
            good[good] = _pieces_agree(tracker, prep, pieces, redo[good], r.alpha[good],
                                       r.w[good], r.zncc[good])[0]
        fixed = redo[good]
        alpha[fixed], t[fixed] = ra[fixed] + r.alpha[good], rt[fixed] + r.w[good]
        zncc[fixed] = r.zncc[good]
        gone = redo[~good]  # lost: they keep their last good pose, as any lost unit
        ok[gone], alpha[gone], t[gone] = False, state.alpha[gone], state.t[gone]
        log.debug("%d poses failed their pieces' check: %d found again, %d flagged lost",
                  redo.size, fixed.size, redo.size - fixed.size)
    return ok, alpha, t, zncc


def _pieces_agree(tracker: DICTracker, prep: PreparedFrame, pieces: Pieces, idx: np.ndarray,
                  alpha: np.ndarray, w: np.ndarray,
                  zncc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(agree [k], moved [k, parts, 2]): whether every piece of units `idx` lands within
    the bound of where their poses (alpha [k], w [k, 2] from the pieces' reference, at
    correlation zncc [k]) put it (units whose pieces cannot be registered pass: nothing to
    check them with), and where each piece's centroid registered, px."""
    cfg = tracker.cfg
    pc = piece_deviation(prep.coef, pieces, idx, alpha, w, zncc, cfg.max_iter,
                         PIECE_TOL_SHARE * cfg.check_floor_px, cfg.max_move_px,
                         lambda rs, i, z: pose_sigma(rs, i, z, cfg.prefilter_sigma_px))
    upper = np.maximum(cfg.check_max_px, cfg.check_sigmas * pc.sigma_fit)
    bound = np.clip(cfg.check_sigmas * pc.sigma, cfg.check_floor_px, upper)
    return ~pc.checkable | np.all(pc.deviation <= bound, axis=1), pc.moved


def pose_sigma(refs: RefSet, idx: np.ndarray, zncc: np.ndarray,
               prefilter_sigma_px: float = 0.0, floor_px=0.0) -> np.ndarray:
    """Standard errors [k, 3] of the registered (wx px, wy px, alpha rad) of units `idx`.

    Two parts in quadrature. Noise: the Gauss-Newton covariance of a least-squares fit,
    sigma_I^2 (J^T J)^-1, with J the steepest-descent images of the reference subset
    (`RefSet.hinv` = (J^T J)^-1, intensity units) and sigma_I^2 the residual variance per
    subset point, read from the correlation (the normalised residual of ZNSSD sums to
    2 (1 - ZNCC), in intensity units times the reference's norm squared, over N - 3 degrees of
    freedom); a prefilter correlates the noise of neighbouring points, which the plain formula
    takes as independent (`noise_correlation_factor`). Systematic: a floor of `floor_px` (one
    value, or one per unit) on every subset point's position, over the subset's RMS radius for
    the rotation (`track_frame` gives `DICConfig.sigma_floor_px` and
    `DICConfig.sigma_blur_share` of the unit's motion since the previous frame, in quadrature). Scaled by `SIGMA_SCALE`, calibrated against truth
    on rendered sequences. A pose off by a wrong match is not covered (the checks flag those).
    """
    idx = np.asarray(idx)
    n = refs.count[idx].astype(np.float64)
    # (the correlation is summed in float32: a residual below its rounding reads as 1 - 1e-7)
    var_i = 2.0 * np.clip(1.0 - np.asarray(zncc, np.float64), 1e-7, None) * refs.df[idx] ** 2 \
        / np.maximum(n - 3.0, 1.0)
    diag = np.diagonal(refs.hinv[idx], axis1=1, axis2=2)
    noise2 = noise_correlation_factor(prefilter_sigma_px) ** 2 * var_i[:, None] * diag
    r2 = refs.r2[idx]
    floor2 = np.asarray(floor_px, np.float64)[..., None] ** 2 * np.stack([np.ones_like(r2), np.ones_like(r2),
                                           1.0 / np.maximum(r2, 1.0)], axis=-1)
    return SIGMA_SCALE * np.sqrt(noise2 + floor2)


def noise_correlation_factor(prefilter_sigma_px: float) -> float:
    """How much a Gaussian prefilter of `prefilter_sigma_px` widens the noise part of
    `pose_sigma`: sqrt(1 + NOISE_AREA_SHARE (A - 1)), A the correlation area of white noise
    after the filter, in pixels (sum of its normalised autocorrelation over the pixel grid);
    1 without a filter."""
    s = float(prefilter_sigma_px)
    if s <= 0:
        return 1.0
    i = np.arange(-int(np.ceil(6 * s)), int(np.ceil(6 * s)) + 1)
    area = float(np.exp(-(i**2) / (4.0 * s * s)).sum()) ** 2
    return float(np.sqrt(1.0 + NOISE_AREA_SHARE * (area - 1.0)))


def acquire_radius(tracker: DICTracker) -> int:
    """Half-width (px) of the first frame's search (`DICConfig.acquire_radius_px`, or auto)."""
    r = tracker.cfg.acquire_radius_px
    if r > 0:
        return int(r)
    height = float(np.ptp(tracker.polys_px[..., 1])) if tracker.n_units else 0.0
    return int(np.ceil(ACQUIRE_STRAIN * height)) + 4


def acquire_frame(tracker: DICTracker, state: TrackerState,
                  prep: PreparedFrame) -> TrackerState:
    """Start poses of every unit in the first frame, searched for, not assumed.

    Units with a search template are matched over `acquire_radius` px and the trial rotations
    around their reference pose; the others start from the rigid motion of their nearest found
    units (IC-GN from each; the best correlation wins). A unit found nowhere starts lost. The
    poses are starting points: `track_frame` then registers and checks them as for any frame.
    """
    cfg = tracker.cfg
    n = tracker.n_units
    refs = state.refs
    usable = np.flatnonzero(refs.count > 0)
    step = max(cfg.acquire_rotation_step, 1e-3)
    k = int(np.floor(cfg.acquire_max_rotation / step + 1e-9))
    rotations = np.r_[0.0, np.ravel(np.column_stack([np.arange(1, k + 1) * step,
                                                      -np.arange(1, k + 1) * step]))]
    alpha, t = np.full(n, np.nan), np.full((n, 2), np.nan)
    # where the reference pose itself registers well (the first frame is the reference, or
    # the sample barely moved), that is the start; the search is for the others
    r = icgn(prep.coef, refs, usable, np.zeros(usable.size), np.zeros((usable.size, 2)),
             cfg.max_iter, cfg.tol_px, cfg.max_move_px)
    near = r.inside & r.converged & (np.nan_to_num(r.zncc, nan=-1.0) >= cfg.zncc_reacquire)
    alpha[usable[near]], t[usable[near]] = r.alpha[near], r.w[near]
    far = usable[~near]
    radius = acquire_radius(tracker)
    w, score = acquire(prep.img, refs, far, np.zeros((far.size, 2)), radius, rotations)
    # verify the best few candidates of each unit with its whole subset; the best wins
    best = np.argsort(-np.nan_to_num(score, nan=-np.inf), axis=1)[:, :ACQUIRE_CANDIDATES]
    rows = np.arange(far.size)[:, None]
    a0 = np.where(np.isfinite(score[rows, best]), rotations[best], np.nan)
    a, ww, zn = _best_of_starts(tracker, refs, prep, far, a0, w[rows, best])
    got = zn >= cfg.zncc_reacquire
    alpha[far[got]], t[far[got]] = a[got], ww[got]
    # units without a found template: the rigid motion of their nearest found units
    anchors = np.flatnonzero(np.isfinite(alpha))
    rest = np.setdiff1d(usable, anchors)
    if rest.size and anchors.size:
        a, w, zn = _from_neighbours(tracker, refs, prep, rest, anchors, alpha, t,
                                    np.zeros(n), np.zeros((n, 2)))
        got = zn >= cfg.zncc_reacquire
        alpha[rest[got]], t[rest[got]] = a[got], w[got]
    ok = np.isfinite(alpha)
    log.info("first frame: %d of %d units found (search radius %d px)", int(ok.sum()),
             int(usable.size), radius)
    return replace(state, alpha=np.where(ok, alpha, 0.0), t=np.where(ok[:, None], t, 0.0),
                   prev_alpha=np.full(n, np.nan), prev_t=np.full((n, 2), np.nan),
                   lost=state.lost | ~ok, acquired=True)


def _from_neighbours(tracker: DICTracker, refs: RefSet, prep: PreparedFrame, units: np.ndarray,
                     anchors: np.ndarray, alpha: np.ndarray, t: np.ndarray,
                     ref_alpha: np.ndarray, ref_t: np.ndarray):
    """Register `units` from the motion of their nearest `anchors` (units whose pose in this
    frame is known: `alpha`, `t` [n], from the reference image): from each neighbour's rigid
    motion carried to the unit, and from the neighbours' mean translation without rotation
    (between counter-rotating neighbours, as in rotating-square lattices, a unit barely turns);
    IC-GN from each start, the best correlation wins. For units a template search cannot find
    (slender ones). Returns (alpha [k], t [k, 2] from the reference image, zncc [k]; -inf where
    nothing converged inside the frame); `ref_alpha`, `ref_t` [n]: each unit's reference pose."""
    c = tracker.centroid_px
    m = min(tracker.cfg.acquire_neighbours, anchors.size)
    d = np.linalg.norm(c[units, None, :] - c[None, anchors, :], axis=-1)
    near = anchors[np.argsort(d, axis=1)[:, :m]]  # [k, m]
    arm = c[units, None, :] - c[near]  # [k, m, 2]
    carried = t[near] + np.einsum("kmij,kmj->kmi", _rot(alpha[near]), arm) - arm
    a0 = np.concatenate([alpha[near], np.zeros((units.size, 1))], axis=1)
    w0 = np.concatenate([carried, t[near].mean(axis=1, keepdims=True)], axis=1)
    a, w, zn = _best_of_starts(tracker, refs, prep, units, a0 - ref_alpha[units, None],
                               w0 - ref_t[units, None, :])
    return ref_alpha[units] + a, ref_t[units] + w, zn


def _best_of_starts(tracker: DICTracker, refs: RefSet, prep: PreparedFrame, units: np.ndarray,
                    a0: np.ndarray, w0: np.ndarray):
    """IC-GN of each of `units` [k] from each of its starts (a0 [k, m] rad, w0 [k, m, 2] px
    relative to its reference; NaN: no start) in one batch; per unit the converged result
    inside the frame with the best correlation: (alpha [k], w [k, 2], zncc [k], -inf where
    none converged)."""
    cfg = tracker.cfg
    k, m = a0.shape
    zn = np.full((k, m), -np.inf)
    al, ww = np.zeros((k, m)), np.zeros((k, m, 2))
    rr, cc = np.nonzero(np.isfinite(a0) & np.all(np.isfinite(w0), axis=-1))
    if rr.size:
        r = icgn(prep.coef, refs, units[rr], a0[rr, cc], w0[rr, cc], cfg.max_iter, cfg.tol_px,
                 cfg.max_move_px)
        zn[rr, cc] = np.where(r.inside & r.converged & np.isfinite(r.zncc), r.zncc, -np.inf)
        al[rr, cc], ww[rr, cc] = r.alpha, r.w
    b, i = np.argmax(zn, axis=1), np.arange(k)
    return al[i, b], ww[i, b], zn[i, b]


def _update_references(
    tracker: DICTracker, state: TrackerState, prep: PreparedFrame, ok: np.ndarray,
    alpha_rel: np.ndarray, zncc: np.ndarray,
) -> TrackerState:
    """Re-extract the reference of good units that rotated far or whose correlation sagged."""
    cfg = tracker.cfg
    need = ok & ((np.abs(alpha_rel) > cfg.max_ref_rotation) | (zncc < cfg.zncc_update))
    idx = np.flatnonzero(need)
    if idx.size == 0:
        return state
    polys, centres = _posed_outlines(tracker, idx, state.alpha[idx], state.t[idx])
    ph = state.refs.patch.shape[1] // 2
    new = build_refs(prep.img, prep.coef, polys, centres, cfg.margin_px, cfg.min_points,
                     patch_half=ph)
    good = new.count > 0
    if not good.any():
        return state
    take = np.flatnonzero(good)
    sub = RefSet(**{k: getattr(new, k)[take] for k in RefSet.__slots__})
    idx = idx[take]
    ref_alpha, ref_t = state.ref_alpha.copy(), state.ref_t.copy()
    ref_alpha[idx], ref_t[idx] = state.alpha[idx], state.t[idx]
    log.debug("reference updated for %d units", idx.size)
    pieces = state.pieces
    if pieces is not None:
        cut = split_refs(sub, pieces.parts)
        pidx = pieces.index(idx).ravel()
        offset = pieces.offset.copy()
        offset[pidx] = cut.offset
        pieces = Pieces(replace_refs(pieces.refs, pidx, cut.refs), offset, pieces.parts)
    return replace(state, refs=replace_refs(state.refs, idx, sub), ref_alpha=ref_alpha,
                   ref_t=ref_t, pieces=pieces)


SMALL_UNIT_MARGIN_PX = 1.5
# the first frame's search covers this strain of the sample's height (`acquire_radius`)
ACQUIRE_STRAIN = 0.1
# `pose_sigma` against the true errors on rendered sequences, before this factor: RMS of
# error / sigma 1.18-1.22 (x, y, theta) on the default `metarig rig` footage (24x16 units of
# 16 px, 1 % read noise, blur), 1.0-1.5 on the synthetic scenes of tests/dic_synth.py (37 and
# 16 px units, 1 and 3 % noise); the reference frame's own noise, which the residual sees only
# once, is the main part left out
SIGMA_SCALE = 1.2
# share of the prefiltered noise's correlation area that the registration sees
# (`noise_correlation_factor`): with it, 95-99 % of the true errors lie within 2 sigma on the
# sharp synthetic scenes of tests/dic_synth.py without a floor (1 and 3 % noise)
NOISE_AREA_SHARE = 0.4
# The systematic part (`DICConfig.sigma_floor_px` 0.005 px, `sigma_blur_share` 0.006): with
# it, 96.6-97.6 % of the true errors lie within 2 sigma (x, y, theta) on the default
# `metarig rig` footage and 94.8-98.3 % on benchmarks/bench_dic_design.py's blurred optimised
# design (x 91 % without the blur share)
# candidates per unit (the best-correlated trial rotations) that the whole subset verifies
ACQUIRE_CANDIDATES = 6
SMALL_UNIT_MIN_POINTS = 16


def settings_for_units(polygons_m: np.ndarray, m_per_px: float,
                       cfg: DICConfig | None = None) -> DICConfig:
    """`cfg` (default settings when None), with a thinner outline margin and a smaller subset
    floor when the smallest unit would otherwise hold fewer than `min_points` subset pixels
    (area minus a `margin_px` band along the perimeter, in px^2): small or slender units in a
    modest image are then tracked instead of lost."""
    from metarig.polygon import signed_areas

    cfg = cfg or DICConfig()
    p = np.asarray(polygons_m, np.float64) / m_per_px
    area = np.abs(signed_areas(p))
    perimeter = np.linalg.norm(p - np.roll(p, -1, axis=-2), axis=-1).sum(axis=-1)
    if np.min(area - perimeter * cfg.margin_px) >= cfg.min_points:
        return cfg
    return replace(cfg, margin_px=min(cfg.margin_px, SMALL_UNIT_MARGIN_PX),
                   min_points=min(cfg.min_points, SMALL_UNIT_MIN_POINTS))
# the pieces of `DICConfig.check_pieces` converge to this share of the check's floor (px): the
# check compares them with a bound of at least the floor, so finer would only cost time
PIECE_TOL_SHARE = 0.1
