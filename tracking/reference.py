"""Reference subsets for batched IC-GN: each unit's interior pixels, padded to a common length.

A unit's subset is every integer pixel of its reference frame that lies inside its outline and
at least `margin_px` from it (so the speckle sampled never mixes with the background or a
neighbour). Everything the inverse-compositional Gauss-Newton needs that depends only on the
reference is computed once here: zero-mean intensities, steepest-descent images for the rigid
warp and the inverse Hessian.
"""

from dataclasses import dataclass

import numpy as np

from metarig.polygon import points_inside


@dataclass(frozen=True, slots=True)
class RefSet:
    """Reference data of n units, padded to M subset points each (pixels, rectified frame).

    Attributes:
        centre_px: [n, 2] (col, row) of the unit's area centroid in its reference frame.
        dx, dy: [n, M] float32 subset point offsets from `centre_px`, px (0 for padding).
        ft: [n, M] float32 zero-mean reference intensities (0 for padding).
        df: [n] norm of `ft` (sqrt of the sum of squares).
        jac: [n, 3, M] float32 steepest-descent images, grad f . dW/dp for the rigid warp
            parameters p = (wx, wy, alpha): translation in px, rotation in rad.
        hinv: [n, 3, 3] inverse Gauss-Newton Hessian.
        sumj: [n, 3] sum of `jac` over the subset. sumjf: [n, 3] sum of `jac * ft`.
        mask: [n, M] float32 1 for real points, 0 for padding.
        count: [n] int number of subset points (0: unit unusable).
        rmax: [n] largest distance of a subset point from the centre, px.
        r2: [n] mean squared distance of the subset points from the centre, px^2.
        patch: [n, P, P] float32 reference pixels around the centre (for coarse search).
        patch_corner: [n, 2] int (col, row) of patch[0, 0] in the reference frame.
        tpl_half: [n] int half-size of the search template that fits inside the subset.
    """

    centre_px: np.ndarray
    dx: np.ndarray
    dy: np.ndarray
    ft: np.ndarray
    df: np.ndarray
    jac: np.ndarray
    hinv: np.ndarray
    sumj: np.ndarray
    sumjf: np.ndarray
    mask: np.ndarray
    count: np.ndarray
    rmax: np.ndarray
    r2: np.ndarray
    patch: np.ndarray
    patch_corner: np.ndarray
    tpl_half: np.ndarray

    @property
    def n(self) -> int:
        return int(self.count.shape[0])


def _edge_distance(px: np.ndarray, verts: np.ndarray) -> np.ndarray:
    """Distance [m] from points px [m, 2] to the closed polyline verts [nv, 2]."""
    a = verts[None, :, :]
    ab = np.roll(verts, -1, axis=0)[None] - a
    ap = px[:, None, :] - a
    t = np.clip((ap * ab).sum(-1) / np.maximum((ab * ab).sum(-1), 1e-30), 0.0, 1.0)
    d = ap - t[..., None] * ab
    return np.sqrt((d * d).sum(-1)).min(axis=1)


def subset_pixels(poly_px: np.ndarray, margin_px: float, shape: tuple[int, int]) -> np.ndarray:
    """Integer pixels [m, 2] (col, row) inside `poly_px` [nv, 2] at least `margin_px` from it.

    Pixels closer than 2 px to the image border are left out (cubic interpolation support).
    Returns an empty array when none remain.
    """
    h, w = shape
    c0 = max(int(np.ceil(poly_px[:, 0].min())), 2)
    c1 = min(int(np.floor(poly_px[:, 0].max())), w - 3)
    r0 = max(int(np.ceil(poly_px[:, 1].min())), 2)
    r1 = min(int(np.floor(poly_px[:, 1].max())), h - 3)
    if c1 < c0 or r1 < r0:
        return np.zeros((0, 2), dtype=np.int64)
    cc, rr = np.meshgrid(np.arange(c0, c1 + 1), np.arange(r0, r1 + 1))
    pts = np.stack([cc.ravel(), rr.ravel()], axis=-1)
    keep = points_inside(pts[:, 0], pts[:, 1], poly_px)
    pts = pts[keep]
    keep = _edge_distance(pts.astype(np.float64), poly_px) >= margin_px
    return pts[keep]


# the subsets of the last outlines asked for: `check_outlines` and the first reference of the
# same units ask for the same (~0.5 s on 384 units)
_last_subsets: tuple | None = None


def unit_subsets(polys_px: np.ndarray, margin_px: float, shape: tuple[int, int]
                 ) -> list[np.ndarray]:
    """`subset_pixels` of every unit of `polys_px` [n, nv, 2] (a list, not to be changed)."""
    global _last_subsets
    key = (polys_px.shape, polys_px.tobytes(), float(margin_px), tuple(shape))
    last = _last_subsets
    if last is not None and last[0] == key:
        return last[1]
    pts = [subset_pixels(p, margin_px, shape) for p in polys_px]
    _last_subsets = (key, pts)
    return pts


def spline_gradients(coef: np.ndarray, rows: np.ndarray, cols: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:
    """d/dcol and d/drow of the cubic B-spline interpolant at the pixel centres (rows, cols)
    (at least 1 px inside the image).

    At integer positions the spline derivative is (c[k+1] - c[k-1]) / 2 of its coefficients,
    so the steepest-descent images are the exact derivatives of the interpolant that IC-GN
    samples. Only the pixels asked for: a reference update re-extracts a few units, and the
    whole frame's gradients cost more than their subsets.
    """
    gx = 0.5 * (coef[rows, cols + 1] - coef[rows, cols - 1])
    gy = 0.5 * (coef[rows + 1, cols] - coef[rows - 1, cols])
    return gx, gy


def build_refs(
    img: np.ndarray,
    coef: np.ndarray,
    polys_px: np.ndarray,
    centres_px: np.ndarray,
    margin_px: float,
    min_points: int = 50,
    patch_half: int | None = None,
) -> RefSet:
    """Extract reference subsets of units from one (pre-filtered, float32) frame.

    Args:
        img: [h, w] float32 reference frame.
        coef: [h, w] its cubic B-spline coefficients.
        polys_px: [n, nv, 2] unit outlines in this frame, pixels (col, row).
        centres_px: [n, 2] area centroids in this frame, pixels.
        margin_px: distance kept from the outline, px.
        min_points: units with fewer subset points are marked unusable (count 0).
        patch_half: half-size of the stored search patch (default: from the subsets).

    Returns:
        The padded `RefSet`.
    """
    n = polys_px.shape[0]
    shape = img.shape
    pts = unit_subsets(np.asarray(polys_px), margin_px, shape)
    pts = [p if p.shape[0] >= min_points else p[:0] for p in pts]
    count = np.array([p.shape[0] for p in pts], dtype=np.int64)
    m = max(int(count.max()), 1)
    dx = np.zeros((n, m), np.float32)
    dy = np.zeros((n, m), np.float32)
    fv = np.zeros((n, m), np.float32)
    jac = np.zeros((n, 3, m), np.float32)
    mask = np.zeros((n, m), np.float32)
    rin = np.zeros(n)
    for b, p in enumerate(pts):
        k = p.shape[0]
        if k == 0:
            continue
        cols, rows = p[:, 0], p[:, 1]
        ddx = cols - centres_px[b, 0]
        ddy = rows - centres_px[b, 1]
        fx, fy = spline_gradients(coef, rows, cols)
        dx[b, :k], dy[b, :k] = ddx, ddy
        fv[b, :k] = img[rows, cols]
        # warp x -> R(alpha)(x - c) + c + w; its derivative at identity
        jac[b, 0, :k], jac[b, 1, :k] = fx, fy
        jac[b, 2, :k] = -fx * ddy + fy * ddx
        mask[b, :k] = 1.0
        rin[b] = _edge_distance(centres_px[b : b + 1], polys_px[b])[0] - margin_px
    cnt = np.maximum(count, 1)
    mean = (fv * mask).sum(axis=1) / cnt
    ft = (fv - mean[:, None].astype(np.float32)) * mask
    df = np.sqrt((ft.astype(np.float64) ** 2).sum(axis=1))
    hess = np.einsum("nim,njm->nij", jac.astype(np.float64), jac.astype(np.float64))
    usable = (count > 0) & (df > 1e-6) & (np.abs(np.linalg.det(hess)) > 1e-12)
    hess[~usable] = np.eye(3)
    hinv = np.linalg.inv(hess)
    jac64 = jac.astype(np.float64)
    sumj = jac64.sum(axis=2)
    sumjf = np.einsum("nim,nm->ni", jac64, ft.astype(np.float64))
    count = np.where(usable, count, 0)
    d2 = dx.astype(np.float64) ** 2 + dy.astype(np.float64) ** 2
    rmax = np.sqrt(d2.max(axis=1))
    r2 = d2.sum(axis=1) / cnt  # padding is at the centre (0)
    tpl_half = np.maximum(np.floor(np.clip(rin, 0, None) / np.sqrt(2.0)).astype(np.int64) - 1, 0)
    ph = patch_half if patch_half is not None else int(np.ceil(max(rin.max(), 1.0))) + 2
    corner = np.rint(centres_px).astype(np.int64) - ph
    patch = np.zeros((n, 2 * ph + 1, 2 * ph + 1), np.float32)
    size = 2 * ph + 1
    reach = ph + 1  # a patch may stick out of the frame this far (zeros there)
    for b in range(n):
        c, r = corner[b]
        if -reach <= r and r + size <= shape[0] + reach and -reach <= c \
                and c + size <= shape[1] + reach:
            r0, c0 = max(r, 0), max(c, 0)
            r1, c1 = min(r + size, shape[0]), min(c + size, shape[1])
            patch[b, r0 - r : r1 - r, c0 - c : c1 - c] = img[r0:r1, c0:c1]
    return RefSet(
        centre_px=np.asarray(centres_px, np.float64).copy(),
        dx=dx, dy=dy, ft=ft, df=df, jac=jac, hinv=hinv, sumj=sumj, sumjf=sumjf, mask=mask, count=count, rmax=rmax,
        r2=r2, patch=patch, patch_corner=corner, tpl_half=tpl_half,
    )


def _pad_to(a: np.ndarray, m: int) -> np.ndarray:
    """Zero-pad the last axis of `a` to length m."""
    if a.shape[-1] >= m:
        return a
    widths = [(0, 0)] * (a.ndim - 1) + [(0, m - a.shape[-1])]
    return np.pad(a, widths)


def replace_refs(refs: RefSet, idx: np.ndarray, new: RefSet, in_place: bool = False) -> RefSet:
    """A copy of `refs` whose units `idx` are replaced by the units of `new` (same order).

    in_place: write the rows into `refs`'s own arrays instead (and return it) where they are
    wide enough: copying every padded array costs more than tracking the frame (~8 ms a frame
    on 384 units); only for arrays nothing else holds (`TrackerState.refs_own`)."""
    m = max(refs.dx.shape[1], new.dx.shape[1])
    if in_place and m == refs.dx.shape[1]:
        for name in RefSet.__slots__:
            new_a, a = getattr(new, name), getattr(refs, name)
            if name in ("dx", "dy", "ft", "jac", "mask"):
                k = new_a.shape[-1]
                a[idx, ..., :k] = new_a
                a[idx, ..., k:] = 0
            else:
                a[idx] = new_a
        return refs
    out = {}
    for name in RefSet.__slots__:
        old_a, new_a = getattr(refs, name), getattr(new, name)
        if name in ("dx", "dy", "ft", "jac", "mask"):
            old_a, new_a = _pad_to(old_a, m), _pad_to(new_a, m)
        a = old_a.copy()
        a[idx] = new_a
        out[name] = a
    return RefSet(**out)

