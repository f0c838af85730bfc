"""Coarse re-acquisition: integer-pixel template search for units that IC-GN lost.

The template is the square inscribed in the unit's subset, cut from its reference patch after
rotating the patch by the unit's predicted rotation (so the square stays inside the speckled
interior at any angle). It is matched by normalised cross-correlation (`cv2.matchTemplate`)
over a window around the predicted position, and the peak refined to sub-pixel by a parabola;
IC-GN then polishes the result.
"""

import cv2
import numpy as np

from tracking.reference import RefSet

# smallest template half-size (px) worth matching: below it a match is not distinctive
MIN_TEMPLATE_HALF = 3


def _rotation(alpha: float) -> np.ndarray:
    c, s = np.cos(alpha), np.sin(alpha)
    return np.array([[c, -s], [s, c]])


def _parabola_peak(left: float, mid: float, right: float) -> float:
    """Sub-sample offset of the vertex of a parabola through three equally spaced values."""
    den = left - 2.0 * mid + right
    if not np.isfinite(den) or den >= 0.0:
        return 0.0
    return float(np.clip(0.5 * (left - right) / den, -0.5, 0.5))


def _match(img: np.ndarray, refs: RefSet, b: int, alpha: float, w_pred: np.ndarray,
           radius_px: int) -> tuple[np.ndarray, float] | None:
    """Template match of unit `b` rotated by `alpha` in a window of half-width `radius_px`
    around the displacement `w_pred` (px): (displacement [2] px, correlation), or None where no
    search is possible (template too small or blank, window outside the frame)."""
    h, wd = img.shape
    ph = refs.patch.shape[1] // 2
    hs = int(refs.tpl_half[b])
    if refs.count[b] == 0 or hs < MIN_TEMPLATE_HALF or not np.all(np.isfinite(w_pred)):
        return None
    rot = _rotation(float(alpha))
    pc = np.array([ph, ph], dtype=np.float64)
    m = np.hstack([rot, (pc - rot @ pc)[:, None]])
    patch = cv2.warpAffine(refs.patch[b], m, (2 * ph + 1, 2 * ph + 1), flags=cv2.INTER_LINEAR)
    tpl = patch[ph - hs : ph + hs + 1, ph - hs : ph + hs + 1]
    if float(tpl.std()) < 1e-6:
        return None
    c_r = refs.centre_px[b]
    rc = (refs.patch_corner[b] + ph).astype(np.float64)  # patch centre pixel, ref frame
    offset = rot @ (rc - c_r) + c_r  # where rc lands, less the displacement
    q = np.rint(offset + w_pred).astype(np.int64)
    c0, r0 = q[0] - hs - radius_px, q[1] - hs - radius_px
    c1, r1 = q[0] + hs + radius_px + 1, q[1] + hs + radius_px + 1
    c0c, r0c, c1c, r1c = max(c0, 0), max(r0, 0), min(c1, wd), min(r1, h)
    if c1c - c0c < 2 * hs + 1 or r1c - r0c < 2 * hs + 1:
        return None
    res = cv2.matchTemplate(img[r0c:r1c, c0c:c1c], tpl, cv2.TM_CCOEFF_NORMED)
    ly, lx = np.unravel_index(int(np.nanargmax(res)), res.shape)
    best = float(res[ly, lx])
    sx = sy = 0.0
    if 0 < lx < res.shape[1] - 1:
        sx = _parabola_peak(res[ly, lx - 1], best, res[ly, lx + 1])
    if 0 < ly < res.shape[0] - 1:
        sy = _parabola_peak(res[ly - 1, lx], best, res[ly + 1, lx])
    found = np.array([c0c + lx + hs + sx, r0c + ly + hs + sy])
    return found - offset, best


def coarse_search(
    img: np.ndarray,
    refs: RefSet,
    idx: np.ndarray,
    alpha: np.ndarray,
    w_pred: np.ndarray,
    radius_px: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Find units `idx` near their predicted displacement by template matching.

    Args:
        img: [h, w] float32 current frame (pre-filtered like the references).
        refs: reference subsets (their patches and template sizes are used).
        idx: [k] unit indices.
        alpha: [k] predicted rotations from the reference, rad (image axes).
        w_pred: [k, 2] predicted centroid displacements from the reference, px.
        radius_px: half-width of the search window around the prediction, px.

    Returns:
        w: [k, 2] displacements at the best match (NaN where no search was possible) and
        score: [k] its normalised correlation (NaN likewise).
    """
    k = len(idx)
    w_out = np.full((k, 2), np.nan)
    score = np.full(k, np.nan)
    for i, b in enumerate(np.asarray(idx)):
        m = _match(img, refs, int(b), float(alpha[i]), w_pred[i], radius_px)
        if m is not None:
            w_out[i], score[i] = m
    return w_out, score


def acquire(
    img: np.ndarray,
    refs: RefSet,
    idx: np.ndarray,
    w_seed: np.ndarray,
    radius_px: int,
    rotations: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Find units `idx` anywhere within `radius_px` of `w_seed` at each of the trial `rotations`
    (rad from the reference): candidates for the first registration of a frame whose units may
    have moved and turned far from the reference (a pre-compressed sample against its unloaded
    image). A small template over a wide window and many rotations can peak at a wrong place
    higher than at the right one, so every rotation's best match is returned for the caller to
    verify with the whole subset (IC-GN).

    Returns:
        w: [k, r, 2] displacement of the best match at each trial rotation, px, and score:
        [k, r] its normalised correlation (NaN where no search was possible: a template under
        `MIN_TEMPLATE_HALF`, which the neighbours' motion must seed instead).
    """
    k, nr = len(idx), len(rotations)
    w_out, score = np.full((k, nr, 2), np.nan), np.full((k, nr), np.nan)
    for i, b in enumerate(np.asarray(idx)):
        if refs.count[b] == 0 or refs.tpl_half[b] < MIN_TEMPLATE_HALF:
            continue  # no template at any rotation
        for j, a in enumerate(rotations):
            m = _match(img, refs, int(b), float(a), w_seed[i], radius_px)
            if m is not None:
                w_out[i, j], score[i, j] = m
    return w_out, score
