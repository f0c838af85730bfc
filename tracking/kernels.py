"""Compiled kernels of the DIC tracker (numba): cubic B-spline prefilter and batched IC-GN.

Why compiled: sub-0.01 px registration needs an interpolant that is exact at any sub-pixel
position. OpenCV's `remap` quantises positions to 1/32 px and its bicubic kernel (a = -0.75)
is only first-order accurate, which biased rotations by ~10 % of their size in tests; scipy's
`map_coordinates` is exact but ~20x too slow for 400 units at camera rates. A cubic B-spline
evaluated in a fused loop that also accumulates the Gauss-Newton sums does one pass per
iteration and stores nothing per point.

Conventions: images are [rows, cols]; positions are (col, row) with pixel centres at integers.
"""

import math
import os

# numba's OpenMP threads otherwise spin between the batches of every frame (GNU OpenMP's
# default "active" wait), burning a core while the reader thread decodes the next frame: on 2
# cores 90 ms of CPU a frame against 60 and 14 s against 6.5 s of wall time for 100 frames of
# the optimised design (benchmarks/bench_dic_design.py). Read when OpenMP starts, at the first
# parallel call; a value set by the user is kept
os.environ.setdefault("OMP_WAIT_POLICY", "passive")

import numpy as np  # noqa: E402
from numba import njit, prange  # noqa: E402

_POLE = math.sqrt(3.0) - 2.0  # pole of the cubic B-spline interpolation filter


@njit(cache=True)
def _filter_line(s: np.ndarray) -> None:
    """In-place cubic B-spline interpolation prefilter of one line (mirror boundaries)."""
    n = s.size
    z = _POLE
    if n == 1:
        return
    # causal initialisation: truncated sum of the mirrored signal (|z|^28 < 1e-16)
    horizon = min(n, 28)
    zk = z
    acc = s[0]
    for k in range(1, horizon):
        acc += zk * s[k]
        zk *= z
    s[0] = acc
    for k in range(1, n):
        s[k] += z * s[k - 1]
    s[n - 1] = (z / (z * z - 1.0)) * (s[n - 1] + z * s[n - 2])
    for k in range(n - 2, -1, -1):
        s[k] = z * (s[k + 1] - s[k])
    for k in range(n):
        s[k] *= 6.0


@njit(cache=True)
def _filter_columns(a: np.ndarray, j0: int, j1: int) -> None:
    """In-place cubic B-spline prefilter along axis 0 of columns j0:j1 of a [h, w] array.

    The same recursion as `_filter_line`, run on row segments so that memory is walked
    contiguously.
    """
    h = a.shape[0]
    z = _POLE
    if h == 1:
        return
    horizon = min(h, 28)
    zk = z
    for k in range(1, horizon):
        for j in range(j0, j1):
            a[0, j] += zk * a[k, j]
        zk *= z
    for i in range(1, h):
        for j in range(j0, j1):
            a[i, j] += z * a[i - 1, j]
    g = z / (z * z - 1.0)
    for j in range(j0, j1):
        a[h - 1, j] = g * (a[h - 1, j] + z * a[h - 2, j])
    for i in range(h - 2, -1, -1):
        for j in range(j0, j1):
            a[i, j] = z * (a[i + 1, j] - a[i, j])
    for i in range(h):
        for j in range(j0, j1):
            a[i, j] *= 6.0


@njit(cache=True, nogil=True)
def bspline_coefficients(img: np.ndarray) -> np.ndarray:
    """Cubic B-spline coefficients [h, w] float32 of an image [h, w] (any real dtype).

    The spline sum_ij c_ij beta3(col - j) beta3(row - i) passes through every pixel value.
    Both passes run down columns of a (transposed, then original) float32 copy: a recursion
    along rows would be latency-bound, one across many columns at once is not. Serial and
    GIL-free, so a reader thread can prepare the next frame while units are being tracked.
    """
    h, w = img.shape
    # float32 work arrays halve memory traffic; the recursion's rounding stays ~1e-4 grey
    tr = np.empty((w, h), dtype=np.float32)
    for i in range(h):
        for j in range(w):
            tr[j, i] = img[i, j]
    _filter_columns(tr, 0, h)
    out = np.ascontiguousarray(tr.T)
    _filter_columns(out, 0, w)
    return out


@njit(cache=True)
def bspline_sample(coef: np.ndarray, px: np.ndarray, py: np.ndarray) -> np.ndarray:
    """Spline values [k] at points (px, py) [k]; NaN where the 4x4 support leaves the image."""
    h, w = coef.shape
    out = np.empty(px.size, dtype=np.float64)
    for m in range(px.size):
        x, y = px[m], py[m]
        ix, iy = math.floor(x), math.floor(y)
        if ix < 1 or iy < 1 or ix > w - 3 or iy > h - 3:
            out[m] = np.nan
            continue
        out[m] = _interp(coef, ix, iy, x - ix, y - iy)
    return out


@njit(cache=True, inline="always")
def _row(coef, r, ix, wx0, wx1, wx2, wx3):
    return (wx0 * coef[r, ix - 1] + wx1 * coef[r, ix] + wx2 * coef[r, ix + 1]
            + wx3 * coef[r, ix + 2])


@njit(cache=True, inline="always")
def _interp(coef, ix, iy, tx, ty):
    """Cubic B-spline value at (ix + tx, iy + ty), 0 <= t < 1, support inside the image."""
    sx = 1.0 - tx
    tx2 = tx * tx
    tx3 = tx2 * tx
    wx0 = sx * sx * sx * (1.0 / 6.0)
    wx3 = tx3 * (1.0 / 6.0)
    wx1 = 0.5 * tx3 - tx2 + (2.0 / 3.0)
    wx2 = 1.0 - wx0 - wx1 - wx3  # the weights sum to 1
    sy = 1.0 - ty
    ty2 = ty * ty
    ty3 = ty2 * ty
    wy0 = sy * sy * sy * (1.0 / 6.0)
    wy3 = ty3 * (1.0 / 6.0)
    wy1 = 0.5 * ty3 - ty2 + (2.0 / 3.0)
    wy2 = 1.0 - wy0 - wy1 - wy3
    return (wy0 * _row(coef, iy - 1, ix, wx0, wx1, wx2, wx3)
            + wy1 * _row(coef, iy, ix, wx0, wx1, wx2, wx3)
            + wy2 * _row(coef, iy + 1, ix, wx0, wx1, wx2, wx3)
            + wy3 * _row(coef, iy + 2, ix, wx0, wx1, wx2, wx3))


@njit(cache=True, fastmath=True, nogil=True)
def _all_inside(dx, dy, n, ca, sa, ox, oy, h, w) -> bool:
    """Whether the 4x4 spline support of every one of the n points (dx, dy) [M], rotated by
    (ca, sa) and moved to (ox, oy), lies inside an [h, w] image (as `bspline_sample` needs)."""
    for m in range(n):
        px = ca * dx[m] - sa * dy[m] + ox
        py = sa * dx[m] + ca * dy[m] + oy
        ix = math.floor(px)
        iy = math.floor(py)
        if ix < 1 or iy < 1 or ix > w - 3 or iy > h - 3:
            return False
    return True


@njit(cache=True, fastmath=True, parallel=True, nogil=True)
def icgn_batch(
    coef, cx, cy, dx, dy, ft, jac, count, hinv, sumj, sumjf, df, rmax,
    idx, alpha, wx, wy, max_iter, tol_px, max_move_px, zncc, conv, inside,
):
    """Rigid IC-GN with ZNSSD for units `idx`, in place on (alpha, wx, wy) and the outputs.

    Units run in parallel on numba threads (`numba.set_num_threads`); call it from one thread
    at a time.

    Warp of a reference point: W(x) = R(alpha) (x - c) + c + w, c = (cx, cy)[b]. With
    e = ft - (df / dg) (g - mean g), the step is dp = -H^-1 sum(J e), expanded into sums that
    one pass over the points accumulates, and the pose is updated by inverse composition.

    Args:
        coef: [h, w] float32 B-spline coefficients of the current frame.
        cx, cy: [n] reference centroid, px. dx, dy: [n, M] point offsets from it, px.
        ft: [n, M] zero-mean reference values. jac: [n, 3, M] steepest-descent images.
        count: [n] points per unit. hinv: [n, 3, 3]. sumj: [n, 3] sum of jac.
        sumjf: [n, 3] sum of jac * ft. df: [n] norm of ft. rmax: [n] subset radius, px.
        idx: [k] units to solve. alpha, wx, wy: [k] start poses, overwritten by solutions.
        max_iter: iteration cap. tol_px: converged when the estimated remaining error (largest
            point displacement, px) is below this.
        max_move_px: give up when the pose moves further than this from its start, px.
        zncc, conv, inside: [k] outputs (ZNCC, converged, subset support inside the image).
    """
    h, w = coef.shape
    for ii in prange(idx.size):  # units are independent: one numba thread each
        b = idx[ii]
        n = count[b]
        zncc[ii] = np.nan
        conv[ii] = False
        inside[ii] = n > 0
        if n == 0:
            continue
        a, tx, ty = alpha[ii], wx[ii], wy[ii]
        a0, tx0, ty0 = a, tx, ty
        prev_step = np.inf
        dxb, dyb, ftb = dx[b], dy[b], ft[b]  # 1-D views: simpler indexing in the hot loop
        j0b, j1b, j2b = jac[b, 0], jac[b, 1], jac[b, 2]
        for _ in range(max_iter):
            ca, sa = math.cos(a), math.sin(a)
            ox, oy = cx[b] + tx, cy[b] + ty
            sg = 0.0
            sgg = 0.0
            sfg = 0.0
            s0 = 0.0
            s1 = 0.0
            s2 = 0.0
            # the whole subset lies within rmax of the centre: check the frame once per unit,
            # point by point only near its edges, in a pass of its own (a test inside the
            # summing loop below, even one never taken, kept it from vectorising: 2x slower)
            reach = rmax[b] + 1e-6
            safe = (ox - reach >= 1.0) and (oy - reach >= 1.0) and (ox + reach < w - 2.0) \
                and (oy + reach < h - 2.0)
            if not safe and not _all_inside(dxb, dyb, n, ca, sa, ox, oy, h, w):
                inside[ii] = False
                break
            for m in range(n):
                ddx, ddy = dxb[m], dyb[m]
                px = ca * ddx - sa * ddy + ox
                py = sa * ddx + ca * ddy + oy
                ix = math.floor(px)
                iy = math.floor(py)
                g = _interp(coef, ix, iy, px - ix, py - iy)
                sg += g
                sgg += g * g
                sfg += ftb[m] * g
                s0 += j0b[m] * g
                s1 += j1b[m] * g
                s2 += j2b[m] * g
            gm = sg / n
            dg2 = sgg - n * gm * gm
            if not dg2 > 1e-9 * (1.0 + sgg):
                zncc[ii] = np.nan
                break
            dg = math.sqrt(dg2)
            zncc[ii] = sfg / (df[b] * dg)
            ratio = df[b] / dg
            r0 = sumjf[b, 0] - ratio * (s0 - gm * sumj[b, 0])
            r1 = sumjf[b, 1] - ratio * (s1 - gm * sumj[b, 1])
            r2 = sumjf[b, 2] - ratio * (s2 - gm * sumj[b, 2])
            d0 = -(hinv[b, 0, 0] * r0 + hinv[b, 0, 1] * r1 + hinv[b, 0, 2] * r2)
            d1 = -(hinv[b, 1, 0] * r0 + hinv[b, 1, 1] * r1 + hinv[b, 1, 2] * r2)
            d2 = -(hinv[b, 2, 0] * r0 + hinv[b, 2, 1] * r1 + hinv[b, 2, 2] * r2)
            # W(p) <- W(p) o W(dp)^-1, exact for rigid motions
            a = a - d2
            c, s = math.cos(a), math.sin(a)
            tx = tx - (c * d0 - s * d1)
            ty = ty - (s * d0 + c * d1)
            moved = math.hypot(tx - tx0, ty - ty0) + abs(a - a0) * rmax[b]
            if not moved <= max_move_px:
                break
            # stop when the error left after this step, estimated from the contraction of
            # successive steps (linear convergence: left = step * rho / (1 - rho)), is below
            # tolerance; saves the confirming iteration a plain step test needs
            step = math.hypot(d0, d1) + abs(d2) * rmax[b]
            rho = step / prev_step
            if step < tol_px * 0.1 or (0.0 < rho < 0.5 and step * rho / (1.0 - rho) < tol_px):
                conv[ii] = True
                break
            prev_step = step
        alpha[ii], wx[ii], wy[ii] = a, tx, ty
