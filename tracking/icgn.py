"""Batched rigid inverse-compositional Gauss-Newton (IC-GN) with the ZNSSD criterion.

Thin numpy front end of `dic_kernels.icgn_batch`: every unit is registered from its own start
pose against its own reference subset (see `dic_reference.RefSet`). The warp of a reference
point x is W(x; wx, wy, alpha) = R(alpha) (x - c) + c + w, with c the unit's centroid in its
reference frame, so alpha is the rotation in image axes (col towards row) and w the centroid
displacement, px.
"""

from dataclasses import dataclass

import numpy as np

from tracking.kernels import icgn_batch
from tracking.reference import RefSet


@dataclass(frozen=True, slots=True)
class IcgnResult:
    """Solution for k units.

    Attributes:
        alpha: [k] rotation from the reference, rad (image axes).
        w: [k, 2] centroid displacement from the reference, px (col, row).
        zncc: [k] zero-normalised cross-correlation at the solution, in [-1, 1] (NaN: blank).
        converged: [k] the last update was below tolerance.
        inside: [k] every subset point (with its interpolation support) lies in the frame.
    """

    alpha: np.ndarray
    w: np.ndarray
    zncc: np.ndarray
    converged: np.ndarray
    inside: np.ndarray


def icgn(
    coef: np.ndarray,
    refs: RefSet,
    idx: np.ndarray,
    alpha0: np.ndarray,
    w0: np.ndarray,
    max_iter: int = 20,
    tol_px: float = 2e-3,
    max_move_px: float = 8.0,
) -> IcgnResult:
    """Register units `idx` of `refs` in the current frame from start poses (alpha0, w0).

    Args:
        coef: [h, w] float32 cubic B-spline coefficients of the current frame.
        refs: reference subsets.
        idx: [k] unit indices into `refs`.
        alpha0: [k] start rotations, rad; w0: [k, 2] start displacements, px.
        max_iter: Gauss-Newton iteration cap.
        tol_px: converged when the estimated remaining error of every subset point is below
            this, px (from the contraction of successive Gauss-Newton steps).
        max_move_px: give up on a unit whose pose wanders further than this from its start.

    Returns:
        The `IcgnResult` for the k units, in the order of `idx`.
    """
    idx = np.ascontiguousarray(idx, dtype=np.int64)
    k = idx.size
    alpha = np.array(alpha0, dtype=np.float64).reshape(k)
    w = np.array(w0, dtype=np.float64).reshape(k, 2)
    wx, wy = w[:, 0].copy(), w[:, 1].copy()
    zncc = np.full(k, np.nan)
    conv = np.zeros(k, dtype=np.bool_)
    inside = np.zeros(k, dtype=np.bool_)
    if k:
        icgn_batch(
            coef, refs.centre_px[:, 0].copy(), refs.centre_px[:, 1].copy(), refs.dx, refs.dy,
            refs.ft, refs.jac, refs.count, refs.hinv, refs.sumj, refs.sumjf, refs.df,
            refs.rmax, idx, alpha, wx, wy, int(max_iter), float(tol_px), float(max_move_px),
            zncc, conv, inside,
        )
    return IcgnResult(alpha, np.stack([wx, wy], axis=1), zncc, conv, inside)
