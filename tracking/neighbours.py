"""A pose checked against its bonded neighbours' motion (pure, no ROS).

Where the tracker knows the lattice's ligaments (`DICTracker.bonds`), each ligament's
end-to-end vector is measured from the poses of the two units it joins: the vector from vertex
k of unit a to vertex l of unit b. A real ligament bends, stretches and turns with its units,
but smoothly; a unit registered on the wrong texture (a neighbour's, a self-similar stretch of
its own) moves its ligaments' ends abruptly. The vector's departure from its rest vector
turned by the units' mean rotation is bounded by `DICConfig.neighbour_static_px`, and, with
three frames of both units' poses, its second difference (its acceleration in px per frame
squared) by `DICConfig.neighbour_px`, the finer test where it applies (not between frames
far apart, as the live preview's: there only the first). A unit whose ligaments
fail to more than half of its tracked bonded neighbours is implausible (`implausible`);
`tracking.dic.track_frame` searches it again from its plausible neighbours' motion and flags it
lost if that fails too.
"""

import numpy as np

from tracking.tracker_state import DICTracker


def vertex_px(tracker: DICTracker, units: np.ndarray, verts: np.ndarray, alpha: np.ndarray,
              t: np.ndarray) -> np.ndarray:
    """Positions [k, 2] (px) of vertex `verts` [k] of `units` [k] at poses alpha [k] (rad),
    t [k, 2] (px) from the outline."""
    c = tracker.centroid_px[units]
    rel = tracker.polys_px[units, verts] - c
    ca, sa = np.cos(alpha), np.sin(alpha)
    return c + t + np.stack([ca * rel[:, 0] - sa * rel[:, 1], sa * rel[:, 0] + ca * rel[:, 1]],
                            axis=-1)


def ligament_excess(tracker: DICTracker, poses: list[tuple[np.ndarray, np.ndarray]],
                    history: np.ndarray) -> np.ndarray:
    """How far each ligament's motion exceeds its bounds (px; > 0 fails), from poses
    [(alpha [n], t [n, 2])] of this frame and the two frames before: the larger of this frame's
    departure from the rest vector turned by the mean rotation (over `neighbour_static_px`) and,
    where `history` [n] holds for both of its units, the second difference (over
    `neighbour_px`)."""
    cfg = tracker.cfg
    a, ka, b, kb = tracker.bonds.T

    def vec(alpha, t):
        return vertex_px(tracker, b, kb, alpha[b], t[b]) - vertex_px(tracker, a, ka, alpha[a], t[a])

    e = [vec(*p) for p in poses]
    rest = tracker.polys_px[b, kb] - tracker.polys_px[a, ka]
    m = 0.5 * (poses[0][0][a] + poses[0][0][b])
    ca, sa = np.cos(m), np.sin(m)
    turned = np.stack([ca * rest[:, 0] - sa * rest[:, 1], sa * rest[:, 0] + ca * rest[:, 1]], -1)
    static = np.linalg.norm(e[0] - turned, axis=-1) - cfg.neighbour_static_px
    if len(e) < 3:
        return static
    acc = np.linalg.norm(e[0] - 2.0 * e[1] + e[2], axis=-1) - cfg.neighbour_px
    with np.errstate(invalid="ignore"):
        return np.maximum(static, np.where(history[a] & history[b] & np.isfinite(acc), acc,
                                           -np.inf))


def implausible(tracker: DICTracker, poses: list[tuple[np.ndarray, np.ndarray]],
                known: np.ndarray, history: np.ndarray) -> np.ndarray:
    """[n] bool: units (of those `known` in this frame) whose ligaments fail (`ligament_excess`)
    to more than half of their known bonded neighbours (a neighbour counts once however many
    ligaments join them): a unit next to a wrong one keeps its other neighbours' support."""
    n = known.size
    a, b = tracker.bonds[:, 0], tracker.bonds[:, 2]
    live = known[a] & known[b]
    fail = live & (ligament_excess(tracker, poses, history) > 0.0)
    pair, inv = np.unique(a * n + b, return_inverse=True)
    pa, pb = pair // n, pair % n
    p_live = np.bincount(inv, weights=live, minlength=pair.size) > 0
    p_fail = np.bincount(inv, weights=fail, minlength=pair.size) > 0
    n_live = np.bincount(pa[p_live], minlength=n) + np.bincount(pb[p_live], minlength=n)
    n_fail = np.bincount(pa[p_fail], minlength=n) + np.bincount(pb[p_fail], minlength=n)
    return known & (2 * n_fail > n_live)
