"""An independent check of a registered pose before it is reported (no ROS, no JAX).

A high correlation is no evidence of a right pose on a slender unit: its rotation is weakly
determined by its subset as a whole, and where the frame shows it as no rigid copy of its
reference (an end blurred, bent or overlapped) whole-subset IC-GN settles on a compromise,
40-120 mrad off at ZNCC 0.91-0.99 in tests, 24-39 mrad off on the optimised design's footage.
The check: the unit's subset is cut into pieces along its long axis (`split_refs`), and each
piece is registered on its own from the pose found (`piece_deviation`). The pieces of a rigid
unit move with it, so each piece's centroid must land where the unit's rigid motion puts it;
a rotation error shows as opposite across-axis shifts of the end pieces, a wrong translation
as the same shift of all. A pose that fails is registered again from its pieces' own rigid
motion (`rigid_fit`) and, failing again, flagged lost (`tracking.dic.track_frame`).
"""

from dataclasses import dataclass

import numpy as np

from tracking.icgn import icgn
from tracking.reference import RefSet


@dataclass(frozen=True, slots=True)
class Pieces:
    """Each unit's subset cut into `parts` pieces, as units of their own for IC-GN.

    Attributes:
        refs: [n * parts] pieces; unit b's are b * parts .. b * parts + parts - 1. A piece
            keeps its points' intensities and gradients; its centre is its own centroid, its
            intensities zero-mean over it and its Hessian its own. count 0: no check possible
            (a piece of fewer than `MIN_PIECE_POINTS` points, or a blank one).
        offset: [n * parts, 2] each piece's centroid from its unit's `centre_px`, px.
        parts: pieces per unit.
    """

    refs: RefSet
    offset: np.ndarray
    parts: int

    def index(self, units: np.ndarray) -> np.ndarray:
        """Piece indices [k, parts] of `units` [k]."""
        return np.asarray(units)[:, None] * self.parts + np.arange(self.parts)


def split_refs(refs: RefSet, parts: int = 2) -> Pieces:
    """Cut each unit's subset of `refs` into `parts` pieces of equal point count along the
    principal axis of its points (the long axis of a sliver, where its rotation shows); nothing
    is read from an image again."""
    if parts < 2:
        raise ValueError(f"parts must be >= 2, got {parts}")
    n, m = refs.dx.shape
    mask = refs.mask > 0
    dx, dy = refs.dx.astype(np.float64), refs.dy.astype(np.float64)
    cnt = np.maximum(refs.count, 1)[:, None]
    mx, my = (dx * mask).sum(1, keepdims=True) / cnt, (dy * mask).sum(1, keepdims=True) / cnt
    cxx = (((dx - mx) ** 2) * mask).sum(1)
    cyy = (((dy - my) ** 2) * mask).sum(1)
    cxy = ((dx - mx) * (dy - my) * mask).sum(1)
    axis = 0.5 * np.arctan2(2.0 * cxy, cxx - cyy)
    along = (dx - mx) * np.cos(axis)[:, None] + (dy - my) * np.sin(axis)[:, None]
    by_axis = np.argsort(np.where(mask, along, np.inf), axis=1, kind="stable")
    rank = np.empty_like(by_axis)  # the inverse permutation: each point's place along the axis
    np.put_along_axis(rank, by_axis, np.arange(m)[None, :], axis=1)
    piece = np.where(mask, rank * parts // cnt, -1)
    src = np.repeat(np.arange(n), parts)
    pm = piece[src] == np.tile(np.arange(parts), n)[:, None]
    k = pm.sum(1)
    usable = np.repeat(np.min(k.reshape(n, parts), axis=1) >= MIN_PIECE_POINTS, parts)
    pm &= usable[:, None]
    k = np.where(usable, k, 0)
    # each piece's points to the front, in their original order (row-major nonzero: each
    # row's columns ascending)
    width = max(int(k.max()), 1)
    rows, cols = np.nonzero(pm)
    order = np.zeros((n * parts, width), np.int64)
    order[rows, np.arange(rows.size) - np.repeat(np.cumsum(k) - k, k)] = cols
    keep = np.arange(width)[None, :] < k[:, None]

    def gather(a):
        return np.where(keep, a[src[:, None], order].astype(np.float64), 0.0)

    kk = np.maximum(k, 1)
    pdx, pdy = gather(refs.dx), gather(refs.dy)
    off = np.stack([pdx.sum(1) / kk, pdy.sum(1) / kk], axis=1)
    pdx = np.where(keep, pdx - off[:, :1], 0.0).astype(np.float32)
    pdy = np.where(keep, pdy - off[:, 1:], 0.0).astype(np.float32)
    f = gather(refs.ft)
    ft = np.where(keep, f - (f.sum(1) / kk)[:, None], 0.0).astype(np.float32)
    fx, fy = gather(refs.jac[:, 0]), gather(refs.jac[:, 1])
    # the rotation's steepest-descent image about the piece's own centre
    jac = np.stack([fx, fy, -fx * pdy + fy * pdx], axis=1).astype(np.float32)
    j64, f64 = jac.astype(np.float64), ft.astype(np.float64)
    hess = np.einsum("nim,njm->nij", j64, j64)
    df = np.sqrt((f64 * f64).sum(1))
    usable &= df > 1e-6
    usable &= np.abs(np.linalg.det(np.where(usable[:, None, None], hess, np.eye(3)))) > 1e-12
    hess[~usable] = np.eye(3)
    hinv = np.linalg.inv(hess)
    rd = np.sqrt(pdx.astype(np.float64) ** 2 + pdy.astype(np.float64) ** 2)
    pieces = RefSet(
        centre_px=refs.centre_px[src] + off, dx=pdx, dy=pdy, ft=ft, df=df, jac=jac,
        hinv=hinv, sumj=j64.sum(2), sumjf=np.einsum("nim,nm->ni", j64, f64),
        mask=keep.astype(np.float32), count=np.where(usable, k, 0), rmax=rd.max(1),
        r2=(rd * rd).sum(1) / kk,
        patch=np.zeros((n * parts, 1, 1), np.float32), patch_corner=refs.patch_corner[src],
        tpl_half=np.zeros(n * parts, np.int64),
    )
    return Pieces(pieces, off, parts)


def _rot(alpha: np.ndarray) -> np.ndarray:
    c, s = np.cos(alpha), np.sin(alpha)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


@dataclass(frozen=True, slots=True)
class PieceCheck:
    """What the pieces of k units say about the units' poses.

    Attributes:
        deviation: [k, parts] distance of each piece's registered centroid from where the
            unit's pose puts it, px (inf where the piece did not register inside the frame).
        sigma: [k, parts] standard error of each piece's centroid position, px, were the
            piece to fit as well as its unit (`tracking.dic.pose_sigma` of the piece at the
            unit's correlation, without a floor: a piece registered off, as it is when the
            unit's pose is wrong, correlates worse and must not widen its own bound).
        sigma_fit: [k, parts] the same at a near-perfect fit (`FIT_ZNCC`): the noise of the
            piece's size alone, which no bound may undercut.
        moved: [k, parts, 2] each piece's registered centroid displacement from the
            reference, px (for `rigid_fit`).
        checkable: [k] every piece of the unit could be registered (count > 0).
    """

    deviation: np.ndarray
    sigma: np.ndarray
    sigma_fit: np.ndarray
    moved: np.ndarray
    checkable: np.ndarray


def piece_deviation(coef: np.ndarray, pieces: Pieces, units: np.ndarray, alpha: np.ndarray,
                    w: np.ndarray, zncc: np.ndarray, max_iter: int, tol_px: float,
                    max_move_px: float, sigma_fn) -> PieceCheck:
    """Register the pieces of `units` [k] from the units' poses and measure their deviation.

    Args:
        coef: [h, w] B-spline coefficients of the frame.
        pieces: pieces of the reference the poses are measured from.
        units: [k] unit indices. alpha: [k] rad, w: [k, 2] px: their poses from that reference.
        zncc: [k] the units' correlation at those poses.
        max_iter, tol_px, max_move_px: IC-GN settings.
        sigma_fn: (refs, idx, zncc) -> [k, 3] standard errors (px, px, rad) of registered poses.
    """
    k, parts = len(units), pieces.parts
    pidx = pieces.index(units).ravel()
    off = pieces.offset[pidx].reshape(k, parts, 2)
    start = np.einsum("kij,kpj->kpi", _rot(alpha), off) - off + w[:, None, :]
    r = icgn(coef, pieces.refs, pidx, np.repeat(alpha, parts), start.reshape(-1, 2), max_iter,
             tol_px, max_move_px)
    moved = r.w.reshape(k, parts, 2)
    dev = np.linalg.norm(moved - start, axis=-1)
    zn = np.nan_to_num(r.zncc, nan=-1.0)
    dev = np.where((r.inside & (zn > -1.0)).reshape(k, parts), dev, np.inf)
    def sigma_at(z):
        sig = sigma_fn(pieces.refs, pidx, z)
        return np.hypot(sig[:, 0], sig[:, 1]).reshape(k, parts)

    sigma = sigma_at(np.repeat(np.nan_to_num(zncc, nan=0.0), parts))
    sigma_fit = sigma_at(np.full(pidx.size, FIT_ZNCC))
    checkable = np.all(pieces.refs.count[pidx].reshape(k, parts) > 0, axis=1)
    return PieceCheck(dev, sigma, sigma_fit, moved, checkable)


# a near-perfect fit (what rendered speckle reaches at rest): `PieceCheck.sigma_fit`
FIT_ZNCC = 0.999
# fewer points than this, and a piece registers too loosely with three degrees of freedom to
# vouch for its unit: its rotation is free and its translation follows it (the 14-point pieces
# of the 10 px units of recordings/precompression-12x8 failed poses as good as their noise)
MIN_PIECE_POINTS = 25


def rigid_fit(offset: np.ndarray, moved: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rigid motion (about the unit's centre) that carries points `offset`
    [k, p, 2] by `moved` [k, p, 2] (px): (alpha [k] rad, w [k, 2] px), the start of a search
    again for a pose its pieces disagreed with."""
    a = offset - offset.mean(axis=1, keepdims=True)
    b = offset + moved
    bc = b - b.mean(axis=1, keepdims=True)
    alpha = np.arctan2((a[..., 0] * bc[..., 1] - a[..., 1] * bc[..., 0]).sum(1),
                       (a * bc).sum(axis=(1, 2)))
    w = b.mean(axis=1) - np.einsum("kij,kj->ki", _rot(alpha), offset.mean(axis=1))
    return alpha, w
