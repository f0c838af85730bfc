"""The first frame tracked is found, not assumed (pure, no ROS): every unit is searched for
over offsets and rotations around its reference position (`acquire_frame`), so the reference
image may show the sample unloaded and the first frame pre-compressed (the rig's procedure);
slender units too small for a search template start from their neighbours' motion
(`from_neighbours`, also the re-acquisition of slender units in `tracking.dic.track_frame`).
"""

import logging
from dataclasses import replace

import numpy as np

from tracking.icgn import icgn
from tracking.reference import RefSet
from tracking.search import acquire
from tracking.tracker_state import DICTracker, PreparedFrame, TrackerState, rot

log = logging.getLogger(__name__)

# the first frame's search covers this strain of the sample's height (`acquire_radius`)
ACQUIRE_STRAIN = 0.1
# candidates per unit (the best-correlated trial rotations) that the whole subset verifies
ACQUIRE_CANDIDATES = 6


def acquire_radius(tracker: DICTracker) -> int:
    """Half-width (px) of the first frame's search (`DICConfig.acquire_radius_px`, or auto)."""
    r = tracker.cfg.acquire_radius_px
    if r > 0:
        return int(r)
    height = float(np.ptp(tracker.polys_px[..., 1])) if tracker.n_units else 0.0
    return int(np.ceil(ACQUIRE_STRAIN * height)) + 4


def acquire_frame(tracker: DICTracker, state: TrackerState, prep: PreparedFrame) -> TrackerState:
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
    rotations = np.r_[
        0.0, np.ravel(np.column_stack([np.arange(1, k + 1) * step, -np.arange(1, k + 1) * step]))
    ]
    alpha, t = np.full(n, np.nan), np.full((n, 2), np.nan)
    # where the reference pose itself registers well (the first frame is the reference, or
    # the sample barely moved), that is the start; the search is for the others
    r = icgn(
        prep.coef,
        refs,
        usable,
        np.zeros(usable.size),
        np.zeros((usable.size, 2)),
        cfg.max_iter,
        cfg.tol_px,
        cfg.max_move_px,
    )
    near = r.inside & r.converged & (np.nan_to_num(r.zncc, nan=-1.0) >= cfg.zncc_reacquire)
    alpha[usable[near]], t[usable[near]] = r.alpha[near], r.w[near]
    far = usable[~near]
    radius = acquire_radius(tracker)
    w, score = acquire(prep.img, refs, far, np.zeros((far.size, 2)), radius, rotations)
    # verify the best few candidates of each unit with its whole subset; the best wins
    best = np.argsort(-np.nan_to_num(score, nan=-np.inf), axis=1)[:, :ACQUIRE_CANDIDATES]
    rows = np.arange(far.size)[:, None]
    a0 = np.where(np.isfinite(score[rows, best]), rotations[best], np.nan)
    a, ww, zn = best_of_starts(tracker, refs, prep, far, a0, w[rows, best])
    got = zn >= cfg.zncc_reacquire
    alpha[far[got]], t[far[got]] = a[got], ww[got]
    # units without a found template: the rigid motion of their nearest found units
    anchors = np.flatnonzero(np.isfinite(alpha))
    rest = np.setdiff1d(usable, anchors)
    if rest.size and anchors.size:
        a, w, zn = from_neighbours(
            tracker, refs, prep, rest, anchors, alpha, t, np.zeros(n), np.zeros((n, 2))
        )
        got = zn >= cfg.zncc_reacquire
        alpha[rest[got]], t[rest[got]] = a[got], w[got]
    ok = np.isfinite(alpha)
    log.info(
        "first frame: %d of %d units found (search radius %d px)",
        int(ok.sum()),
        int(usable.size),
        radius,
    )
    return replace(
        state,
        alpha=np.where(ok, alpha, 0.0),
        t=np.where(ok[:, None], t, 0.0),
        prev_alpha=np.full(n, np.nan),
        prev_t=np.full((n, 2), np.nan),
        lost=state.lost | ~ok,
        acquired=True,
    )


def from_neighbours(
    tracker: DICTracker,
    refs: RefSet,
    prep: PreparedFrame,
    units: np.ndarray,
    anchors: np.ndarray,
    alpha: np.ndarray,
    t: np.ndarray,
    ref_alpha: np.ndarray,
    ref_t: np.ndarray,
):
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
    carried = t[near] + np.einsum("kmij,kmj->kmi", rot(alpha[near]), arm) - arm
    a0 = np.concatenate([alpha[near], np.zeros((units.size, 1))], axis=1)
    w0 = np.concatenate([carried, t[near].mean(axis=1, keepdims=True)], axis=1)
    a, w, zn = best_of_starts(
        tracker, refs, prep, units, a0 - ref_alpha[units, None], w0 - ref_t[units, None, :]
    )
    return ref_alpha[units] + a, ref_t[units] + w, zn


def best_of_starts(
    tracker: DICTracker,
    refs: RefSet,
    prep: PreparedFrame,
    units: np.ndarray,
    a0: np.ndarray,
    w0: np.ndarray,
):
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
        r = icgn(
            prep.coef,
            refs,
            units[rr],
            a0[rr, cc],
            w0[rr, cc],
            cfg.max_iter,
            cfg.tol_px,
            cfg.max_move_px,
        )
        zn[rr, cc] = np.where(r.inside & r.converged & np.isfinite(r.zncc), r.zncc, -np.inf)
        al[rr, cc], ww[rr, cc] = r.alpha, r.w
    b, i = np.argmax(zn, axis=1), np.arange(k)
    return al[i, b], ww[i, b], zn[i, b]
