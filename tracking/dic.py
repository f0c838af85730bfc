"""DIC tracker: sub-pixel rigid pose of every unit in every frame (pure logic, no ROS).

Per frame: predict each unit's pose (constant velocity), register it by rigid IC-GN with
ZNSSD against the unit's reference subset, re-acquire units whose correlation dropped by a
template search around the prediction, flag as lost (pose NaN, never guessed) those still
poor or whose subset leaves the frame, and refresh the reference of the units that need it
(rotated far from their reference, or correlation degraded). All units are solved in one
compiled batch; the offline CLI and the live node call the same `track_frame`.

The first frame tracked is found, not assumed (`tracking.first_frame`); every pose is checked
(`tracking.checks`, and against its bonded neighbours where the lattice is known:
`tracking.neighbours`) and carries a standard error (`tracking.pose_sigma`).

The problem and its state are `tracking.tracker_state`, the settings `tracking.dic_config`;
this module re-exports the public names of both (the tracker's one import path).
"""

import logging
from dataclasses import dataclass, replace

import numpy as np

from tracking.checks import Pieces, piece_deviation, rigid_fit, split_refs
from tracking.dic_config import SMALL_UNIT_MARGIN_PX as SMALL_UNIT_MARGIN_PX
from tracking.dic_config import SMALL_UNIT_MIN_POINTS as SMALL_UNIT_MIN_POINTS
from tracking.dic_config import DICConfig as DICConfig
from tracking.dic_config import settings_for_units as settings_for_units
from tracking.first_frame import acquire_frame as acquire_frame
from tracking.first_frame import acquire_radius as acquire_radius
from tracking.first_frame import from_neighbours
from tracking.icgn import icgn
from tracking.neighbours import implausible
from tracking.pose_sigma import NOISE_AREA_SHARE as NOISE_AREA_SHARE
from tracking.pose_sigma import SIGMA_SCALE as SIGMA_SCALE
from tracking.pose_sigma import noise_correlation_factor as noise_correlation_factor
from tracking.pose_sigma import pose_sigma as pose_sigma
from tracking.reference import RefSet, build_refs, replace_refs
from tracking.search import MIN_TEMPLATE_HALF, coarse_search
from tracking.tracker_state import DICTracker as DICTracker
from tracking.tracker_state import FrameError as FrameError
from tracking.tracker_state import FramePoses as FramePoses
from tracking.tracker_state import PreparedFrame as PreparedFrame
from tracking.tracker_state import TrackerState as TrackerState
from tracking.tracker_state import all_lost as all_lost
from tracking.tracker_state import init_state as init_state
from tracking.tracker_state import posed_outlines, to_sample
from tracking.tracker_state import prepare_frame as prepare_frame

log = logging.getLogger(__name__)

# the pieces of `DICConfig.check_pieces` converge to this share of the check's floor (px): the
# check compares them with a bound of at least the floor, so finer would only cost time
PIECE_TOL_SHARE = 0.1


@dataclass(frozen=True, slots=True)
class WorkingPoses:
    """One frame's poses while `track_frame` checks them (rectified pixel axes). Each check
    takes a record and returns a new one, writing only its own copies of the arrays.

    Attributes:
        ok: [n] the pose is good; a unit that is not keeps its last good pose (it is lost).
        checked: [n] the pose is registered against the reference image (`TrackerState.refs0`),
            not against the unit's refreshed reference.
        alpha: [n] rotation of each unit from the outline, rad.
        t: [n, 2] centroid displacement of each unit from the outline, px.
        zncc: [n] correlation of the registration each pose comes from.
    """

    ok: np.ndarray
    checked: np.ndarray
    alpha: np.ndarray
    t: np.ndarray
    zncc: np.ndarray

    def copy(self) -> "WorkingPoses":
        """The same poses in arrays of its own (for a check to write)."""
        return WorkingPoses(
            self.ok.copy(), self.checked.copy(), self.alpha.copy(), self.t.copy(), self.zncc.copy()
        )


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
        why). `state` is consumed (its reference arrays may be updated in place,
        `TrackerState.refs_own`): go on from the state returned.
    """
    cfg = tracker.cfg
    try:
        prep = frame if isinstance(frame, PreparedFrame) else prepare_frame(tracker, frame)
        if prep.img.shape != state.shape:
            raise FrameError(
                f"frame size {prep.img.shape} differs from the reference {state.shape}"
            )
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
        r = icgn(
            prep.coef,
            refs,
            tracked,
            a0[tracked],
            w0[tracked],
            cfg.max_iter,
            cfg.tol_px,
            cfg.max_move_px,
        )
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
            r = icgn(
                prep.coef,
                refs,
                cand,
                a0[cand],
                ws[found],
                cfg.max_iter,
                cfg.tol_px,
                cfg.max_move_px,
            )
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
        a, tt, zn = from_neighbours(
            tracker, refs, prep, slim, anchors, a_abs, t_abs, state.ref_alpha, state.ref_t
        )
        got = zn >= cfg.zncc_reacquire
        sel = slim[got]
        alpha[sel], w[sel] = a[got] - state.ref_alpha[sel], tt[got] - state.ref_t[sel]
        zncc[sel], ok[sel] = zn[got], True

    # new poses: good units move on, the others keep their last good pose and are lost
    new_alpha = np.where(ok, state.ref_alpha + np.nan_to_num(alpha), state.alpha)
    new_t = np.where(ok[:, None], state.ref_t + np.nan_to_num(w), state.t)
    poses = _check_poses(
        tracker, state, prep, WorkingPoses(ok, np.zeros(n, bool), new_alpha, new_t, zncc)
    )
    ok, checked, new_alpha, new_t = poses.ok, poses.checked, poses.alpha, poses.t
    src_zncc = poses.zncc
    src_refs = [(refs, ok & ~checked, src_zncc), (state.refs0, ok & checked, src_zncc)]
    prev_alpha = np.where(ok & ~state.lost, state.alpha, np.nan)
    prev_t = np.where((ok & ~state.lost)[:, None], state.t, np.nan)
    # motion since the previous frame (px at the subset's edge; 0 where unknown): blur's scale
    moved = np.nan_to_num(
        np.hypot(*(new_t - prev_t).T) + np.abs(new_alpha - prev_alpha) * refs.rmax
    )
    q = np.full((n, 3), np.nan)
    q[ok] = to_sample(tracker, new_alpha[ok], new_t[ok])
    sigma = np.full((n, 3), np.nan)
    cal = tracker.calib
    for rs, sel, zn in src_refs:  # before the references are updated (in place)
        if sel.any():
            floor = np.hypot(cfg.sigma_floor_px, cfg.sigma_blur_share * moved[sel])
            sigma[sel] = pose_sigma(
                rs, np.flatnonzero(sel), zn[sel], cfg.prefilter_sigma_px, floor
            ) * np.array([cal.m_per_px, cal.m_per_px, 1.0])
    state = replace(state, alpha=new_alpha, t=new_t, prev_alpha=prev_alpha, prev_t=prev_t, lost=~ok)
    state = _update_references(tracker, state, prep, ok, new_alpha - state.ref_alpha, src_zncc)
    return state, FramePoses(q=q, quality=src_zncc, lost=~ok, sigma=sigma)


def _check_poses(
    tracker: DICTracker, state: TrackerState, prep: PreparedFrame, poses: WorkingPoses
) -> WorkingPoses:
    """Run the checks the state and problem allow on a frame's poses, in order: against the
    reference image, by pieces, against the bonded neighbours."""
    if state.refs0 is not None:
        poses = _verify_against_reference(tracker, state, prep, poses)
    if state.pieces is not None:
        poses = _check_by_pieces(tracker, state, prep, poses)
    if tracker.bonds is not None and tracker.bonds.size and tracker.cfg.neighbour_px > 0:
        poses = _check_neighbours(tracker, state, prep, poses)
    return poses


def _verify_against_reference(
    tracker: DICTracker, state: TrackerState, prep: PreparedFrame, poses: WorkingPoses
) -> WorkingPoses:
    """Check the poses registered against a refreshed reference with the reference image's own
    subsets (drift-free: a refreshed reference taken at a slightly wrong pose carries that error
    into every later frame, at a high correlation). Where the original subset registers well
    from the pose found, its pose is the one reported; where it registers poorly but agrees
    within `DICConfig.verify_px` / `verify_rad`, the pose stands; otherwise the unit is lost.

    Returns the verified poses; `checked` marks those the original reference now vouches for."""
    cfg = tracker.cfg
    refreshed = poses.ok & ((state.ref_alpha != 0.0) | np.any(state.ref_t != 0.0, axis=1))
    if not refreshed.any():
        return poses
    alpha, t = poses.alpha, poses.t
    idx = np.flatnonzero(refreshed)
    r = icgn(
        prep.coef, state.refs0, idx, alpha[idx], t[idx], cfg.max_iter, cfg.tol_px, cfg.max_move_px
    )
    z0 = np.nan_to_num(r.zncc, nan=-1.0)
    good = r.inside & r.converged & (z0 >= cfg.zncc_reacquire)
    rmax = state.refs0.rmax[idx]
    agree = (np.abs(r.alpha - alpha[idx]) <= cfg.verify_rad) & (
        np.hypot(*(r.w - t[idx]).T) + rmax * np.abs(r.alpha - alpha[idx]) <= cfg.verify_px
    )
    fair = r.inside & (z0 >= cfg.zncc_lost) & agree
    p = poses.copy()
    take = idx[good]
    p.alpha[take], p.t[take], p.zncc[take] = r.alpha[good], r.w[good], r.zncc[good]
    p.checked[take] = True
    bad = idx[~good & ~fair]
    if bad.size:
        log.debug("%d poses disagree with the reference image: flagged lost", bad.size)
    p.ok[bad] = False
    return p


def _check_by_pieces(
    tracker: DICTracker, state: TrackerState, prep: PreparedFrame, poses: WorkingPoses
) -> WorkingPoses:
    """Check every good pose with its unit's pieces (`tracking.checks`), each against the
    reference it was registered with (the reference image's where `checked`). A unit whose
    pieces disagree is registered again from their own rigid motion; if its pieces disagree
    with that too, or it correlates below `zncc_lost`, it is lost.

    Returns the poses after the check (`checked` unchanged)."""
    cfg = tracker.cfg
    p = poses.copy()
    ok, alpha, t, zncc = p.ok, p.alpha, p.t, p.zncc
    zero_a, zero_t = np.zeros_like(state.ref_alpha), np.zeros_like(state.ref_t)
    for refs, pieces, ra, rt, sel in (
        (state.refs, state.pieces, state.ref_alpha, state.ref_t, ok & ~p.checked),
        (state.refs0, state.pieces0, zero_a, zero_t, ok & p.checked),
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
            good[good] = _pieces_agree(
                tracker, prep, pieces, redo[good], r.alpha[good], r.w[good], r.zncc[good]
            )[0]
        fixed = redo[good]
        alpha[fixed], t[fixed] = ra[fixed] + r.alpha[good], rt[fixed] + r.w[good]
        zncc[fixed] = r.zncc[good]
        gone = redo[~good]  # lost: they keep their last good pose, as any lost unit
        ok[gone], alpha[gone], t[gone] = False, state.alpha[gone], state.t[gone]
        log.debug(
            "%d poses failed their pieces' check: %d found again, %d flagged lost",
            redo.size,
            fixed.size,
            redo.size - fixed.size,
        )
    return p


def _check_neighbours(
    tracker: DICTracker, state: TrackerState, prep: PreparedFrame, poses: WorkingPoses
) -> WorkingPoses:
    """Check every good pose against its bonded neighbours' motion (`tracking.neighbours`). An
    implausible unit is registered again against the reference image from its plausible
    neighbours' motion (`from_neighbours`); the pose found stands if it correlates to
    `zncc_reacquire`, its ligaments pass and its pieces agree, else the unit is lost.

    Returns the poses after the check (those found again are now `checked`: registered
    against the reference image)."""
    cfg = tracker.cfg
    history = ~state.lost & np.isfinite(state.prev_alpha)
    before = [(state.alpha, state.t), (state.prev_alpha, state.prev_t)]
    bad = implausible(tracker, [(poses.alpha, poses.t), *before], poses.ok, history)
    if not bad.any():
        return poses
    p = poses.copy()
    ok, alpha, t, zncc = p.ok, p.alpha, p.t, p.zncc
    redo, anchors = np.flatnonzero(bad), np.flatnonzero(ok & ~bad)
    fixed = np.zeros(redo.size, bool)
    if anchors.size and state.refs0 is not None:
        zero_a, zero_t = np.zeros_like(alpha), np.zeros_like(t)
        a, w, zn = from_neighbours(
            tracker, state.refs0, prep, redo, anchors, alpha, t, zero_a, zero_t
        )
        fixed = zn >= cfg.zncc_reacquire
        if fixed.any():
            trial_a, trial_t, known = alpha.copy(), t.copy(), ok & ~bad
            trial_a[redo[fixed]], trial_t[redo[fixed]], known[redo[fixed]] = a[fixed], w[fixed], True
            fixed &= ~implausible(tracker, [(trial_a, trial_t), *before], known, history)[redo]
        if fixed.any() and state.pieces0 is not None:
            fixed[fixed] = _pieces_agree(
                tracker, prep, state.pieces0, redo[fixed], a[fixed], w[fixed], zn[fixed]
            )[0]
        take = redo[fixed]
        alpha[take], t[take], zncc[take] = a[fixed], w[fixed], zn[fixed]
        p.checked[take] = True
    gone = redo[~fixed]  # lost: they keep their last good pose, as any lost unit
    ok[gone], alpha[gone], t[gone] = False, state.alpha[gone], state.t[gone]
    log.debug(
        "%d poses disagree with their neighbours: %d found again, %d flagged lost",
        redo.size,
        redo.size - gone.size,
        gone.size,
    )
    return p


def _pieces_agree(
    tracker: DICTracker,
    prep: PreparedFrame,
    pieces: Pieces,
    idx: np.ndarray,
    alpha: np.ndarray,
    w: np.ndarray,
    zncc: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """(agree [k], moved [k, parts, 2]): whether every piece of units `idx` lands within
    the bound of where their poses (alpha [k], w [k, 2] from the pieces' reference, at
    correlation zncc [k]) put it (units whose pieces cannot be registered pass: nothing to
    check them with), and where each piece's centroid registered, px."""
    cfg = tracker.cfg
    pc = piece_deviation(
        prep.coef,
        pieces,
        idx,
        alpha,
        w,
        zncc,
        cfg.max_iter,
        PIECE_TOL_SHARE * cfg.check_floor_px,
        cfg.max_move_px,
        lambda rs, i, z: pose_sigma(rs, i, z, cfg.prefilter_sigma_px),
    )
    upper = np.maximum(cfg.check_max_px, cfg.check_sigmas * pc.sigma_fit)
    bound = np.clip(cfg.check_sigmas * pc.sigma, cfg.check_floor_px, upper)
    return ~pc.checkable | np.all(pc.deviation <= bound, axis=1), pc.moved


def _update_references(
    tracker: DICTracker,
    state: TrackerState,
    prep: PreparedFrame,
    ok: np.ndarray,
    alpha_rel: np.ndarray,
    zncc: np.ndarray,
) -> TrackerState:
    """Re-extract the reference of good units that rotated far or whose correlation sagged."""
    cfg = tracker.cfg
    need = ok & ((np.abs(alpha_rel) > cfg.max_ref_rotation) | (zncc < cfg.zncc_update))
    idx = np.flatnonzero(need)
    if idx.size == 0:
        return state
    polys, centres = posed_outlines(tracker, idx, state.alpha[idx], state.t[idx])
    ph = state.refs.patch.shape[1] // 2
    new = build_refs(
        prep.img, prep.coef, polys, centres, cfg.margin_px, cfg.min_points, patch_half=ph
    )
    good = new.count > 0
    if not good.any():
        return state
    take = np.flatnonzero(good)
    sub = RefSet(**{k: getattr(new, k)[take] for k in RefSet.__slots__})
    idx = idx[take]
    ref_alpha, ref_t = state.ref_alpha.copy(), state.ref_t.copy()
    ref_alpha[idx], ref_t[idx] = state.alpha[idx], state.t[idx]
    log.debug("reference updated for %d units", idx.size)
    own = state.refs_own  # else refs and pieces are still refs0's and pieces0's: copied
    pieces = state.pieces
    if pieces is not None:
        cut = split_refs(sub, pieces.parts)
        pidx = pieces.index(idx).ravel()
        offset = pieces.offset if own else pieces.offset.copy()
        offset[pidx] = cut.offset
        pieces = Pieces(replace_refs(pieces.refs, pidx, cut.refs, own), offset, pieces.parts)
    return replace(
        state,
        refs=replace_refs(state.refs, idx, sub, own),
        ref_alpha=ref_alpha,
        ref_t=ref_t,
        pieces=pieces,
        refs_own=True,
    )
