"""Synthetic high-speed camera: renders speckled rigid units with exact ground truth.

Each unit is a polygon carrying its own speckle pattern, fixed in its body. The pattern is an
analytic function (a sum of isotropic Gaussian blobs in body coordinates), evaluated at
`supersample x supersample` points inside every pixel and box-averaged, so a rendered frame is
the pixel integral of the scene with no interpolation anywhere: a tracker's error against the
poses given here is the tracker's own. Because a rigid motion preserves distances, every blob
factorises into a row term times a column term on the (axis-aligned) sub-pixel grid, so the
speckle sum over a unit's bounding box is one small matrix product.

Pixel convention (as OpenCV, and as `metarig track`): pixel (col, row) has its centre at integer
coordinates; a sample-frame point (x, y) in metres lies at col = origin_px[0] + x / m_per_px
and row = origin_px[1] - y / m_per_px when `y_up` (row = origin_px[1] + y / m_per_px otherwise).

Pure functions of (config, inputs, rng); no ROS imports. The blob sum is a small compiled
loop over each blob's footprint (a BLAS matrix product would do the same work, but threaded
BLAS on small matrices crawls when the cores are shared); the outline test and the pixel
averaging run in the same compiled loop (`_unit_block`: the same 8-bit frames as the numpy
version of these, in 0.45x its CPU time on an 8x6 sample at 340x260).
"""

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numba import njit

from metarig.fields import param
from metarig.polygon import area_centroids

FULL_SCALE = 255.0  # grey levels of an 8-bit frame


@dataclass(frozen=True, slots=True)
class CameraConfig:
    """Camera, optics, lighting and speckle parameters (each field's description, unit and
    bounds in its metadata). Frame k is at t = k / fps; `origin_px` and `y_up` place the sample
    frame in the image (see the module docstring); `exposure_samples` is used with
    `render_frame`'s `motion_from`, the mid-exposure pose being the natural ground truth."""

    width_px: int = param(640, "frame width, px", 1, 100000)
    height_px: int = param(480, "frame height, px", 1, 100000)
    fps: float = param(1000.0, "frame rate, 1/s (frame k is at t = k / fps)", 1e-6, 1e7)
    m_per_px: float = param(6.0e-4, "scale of the (square-on) image, m/px", 1e-9, 1.0)
    origin_px: tuple[float, float] = param(
        (20.0, 460.0), "(col, row) pixel position of the sample-frame origin, px"
    )
    y_up: bool = param(True, "sample y axis points up the image (rows grow downwards)")
    supersample: int = param(4, "sub-pixel samples per pixel side for pixel integration", 1, 16)
    background_level: float = param(15.0, "grey level of the empty table (0-255)", 0.0, 255.0)
    unit_level: float = param(45.0, "grey level of a unit's bare surface (0-255)", 0.0, 255.0)
    speckle_level: float = param(
        225.0, "grey level a fully covered speckle saturates to (0-255)", 0.0, 255.0
    )
    occluder_level: float = param(
        128.0, "grey level painted over occluded pixels (0-255)", 0.0, 255.0
    )
    speckle_sigma_m: float = param(7.5e-4, "Gaussian radius of one speckle blob, m", 1e-9, 1.0)
    speckle_fill: float = param(
        0.7,
        "mean blob overlap (expected sum of blob profiles at a "
        "point; 0.5-1 gives a well-contrasted pattern)",
        0.0,
        10.0,
    )
    exposure_samples: int = param(5, "sub-exposures averaged for motion blur", 1, 64)
    blur_sigma_px: float = param(0.0, "Gaussian optical blur, px (0: none)", 0.0, 100.0)
    noise_std: float = param(
        0.0, "Gaussian read noise, fraction of full scale (0.02: 2 %)", 0.0, 1.0
    )
    full_well: float = param(
        0.0, "photo-electrons at full scale for shot noise (0: none)", 0.0, 1e9
    )
    lighting_gradient: float = param(
        0.0, "relative intensity change from the left to the right edge", -1.0, 1.0
    )
    vignetting: float = param(
        0.0, "relative intensity drop at the frame corners (quadratic in radius)", 0.0, 1.0
    )
    seed: int = param(0, "default seed for `camera_rng`", 0, 2**63 - 1)

    def __post_init__(self):
        if self.width_px < 1 or self.height_px < 1:
            raise ValueError(f"frame size must be positive, got {self.width_px}x{self.height_px}")
        if not (self.m_per_px > 0 and self.fps > 0 and self.speckle_sigma_m > 0):
            raise ValueError("m_per_px, fps and speckle_sigma_m must be > 0")
        if self.supersample < 1 or self.exposure_samples < 1:
            raise ValueError("supersample and exposure_samples must be >= 1")
        if self.noise_std < 0 or self.full_well < 0 or self.blur_sigma_px < 0:
            raise ValueError("noise_std, full_well and blur_sigma_px must be >= 0")


@dataclass(frozen=True, slots=True)
class SpeckleTextures:
    """Speckle blobs fixed in each unit's body.

    Attributes:
        centres_m: [n_units, n_blobs, 2] blob centres relative to the unit's area centroid in
            its reference orientation, m (padding rows are 0 with weight 0).
        weights: [n_units, n_blobs] blob amplitudes (1 for a blob, 0 for padding).
        sigma_m: blob Gaussian radius, m.
    """

    centres_m: np.ndarray
    weights: np.ndarray
    sigma_m: float


def square_lattice_polygons(
    nx: int, ny: int, pitch_m: float, side_m: float, origin_m: tuple[float, float] = (0.0, 0.0)
) -> np.ndarray:
    """Outlines [nx * ny, 4, 2] (m) of square units on a square grid, row-major, x fastest.

    Unit (i, j) is centred at origin_m + (i, j) * pitch_m; vertices are counter-clockwise.
    """
    cx, cy = np.meshgrid(np.arange(nx) * pitch_m, np.arange(ny) * pitch_m)
    centres = np.stack([cx.ravel(), cy.ravel()], axis=-1) + np.asarray(origin_m)
    corners = 0.5 * side_m * np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])
    return centres[:, None, :] + corners[None, :, :]


def camera_rng(cfg: CameraConfig) -> np.random.Generator:
    """The camera's seeded random generator (`cfg.seed`)."""
    return np.random.default_rng(cfg.seed)


def sample_to_pixel(cfg: CameraConfig, xy_m: np.ndarray) -> np.ndarray:
    """Map sample-frame points (m, [..., 2]) to pixel (col, row) coordinates ([..., 2])."""
    xy = np.asarray(xy_m, dtype=np.float64)
    sy = -1.0 if cfg.y_up else 1.0
    col = cfg.origin_px[0] + xy[..., 0] / cfg.m_per_px
    row = cfg.origin_px[1] + sy * xy[..., 1] / cfg.m_per_px
    return np.stack([col, row], axis=-1)


def make_speckle_textures(
    polygons_m: np.ndarray, cfg: CameraConfig, rng: np.random.Generator
) -> SpeckleTextures:
    """Draw a random speckle pattern for every unit.

    Blob centres are uniform over each unit's bounding box grown by 3 blob radii (so the pattern
    runs to the edges), their number Poisson with mean `speckle_fill * area / (2 pi sigma^2)`.

    Args:
        polygons_m: [n_units, n_vertices, 2] reference outlines in the sample frame, m.
        cfg: camera configuration (speckle size and fill).
        rng: random generator.

    Returns:
        The textures, in body coordinates relative to each area centroid.
    """
    poly = np.asarray(polygons_m, dtype=np.float64)
    rel = poly - area_centroids(poly)[:, None, :]
    sig = cfg.speckle_sigma_m
    lo = rel.min(axis=1) - 3.0 * sig
    hi = rel.max(axis=1) + 3.0 * sig
    box_area = np.prod(hi - lo, axis=1)
    counts = rng.poisson(cfg.speckle_fill * box_area / (2.0 * np.pi * sig**2))
    n_max = max(int(counts.max()), 1)
    centres = np.zeros((poly.shape[0], n_max, 2))
    weights = np.zeros((poly.shape[0], n_max))
    for b, n in enumerate(counts):
        centres[b, :n] = lo[b] + rng.random((n, 2)) * (hi[b] - lo[b])
        weights[b, :n] = 1.0
    return SpeckleTextures(centres_m=centres, weights=weights, sigma_m=sig)


_CUTOFF = 1e-9  # blob factors below this are dropped (their sum is far below a grey level)


@njit(cache=True)
def _unit_block(
    e_row: np.ndarray,
    e_col: np.ndarray,
    gx: np.ndarray,
    gy: np.ndarray,
    verts: np.ndarray,
    amp: float,
    base: float,
    ss: int,
) -> np.ndarray:
    """One unit's radiance over its bounding box, box-averaged to pixels [n_rows, n_cols].

    At sub-pixel (j, i): speckle s = sum_k e_row[k, j] * e_col[k, i] over each blob's
    footprint (factors below `_CUTOFF` dropped), radiance amp (1 - exp(-s)) + base inside the
    outline `verts` [nv, 2] (even-odd rule, `metarig.polygon.points_inside`'s arithmetic) and 0
    outside, at sub-pixel coordinates (gx[i], gy[j]); each pixel the mean of its ss x ss."""
    k_n, nj = e_row.shape
    ni = e_col.shape[1]
    speckle = np.zeros((nj, ni))
    for k in range(k_n):
        j0 = 0
        while j0 < nj and e_row[k, j0] < _CUTOFF:
            j0 += 1
        j1 = nj
        while j1 > j0 and e_row[k, j1 - 1] < _CUTOFF:
            j1 -= 1
        i0 = 0
        while i0 < ni and e_col[k, i0] < _CUTOFF:
            i0 += 1
        i1 = ni
        while i1 > i0 and e_col[k, i1 - 1] < _CUTOFF:
            i1 -= 1
        ek = e_col[k, i0:i1]
        n = i1 - i0
        for j in range(j0, j1):
            r = e_row[k, j]
            sj = speckle[j, i0:i1]
            for i in range(n):  # from 0: no negative-index wrap-around, so it vectorises
                sj[i] += r * ek[i]
    nv = verts.shape[0]
    out = np.zeros((nj // ss, ni // ss))
    crossing = np.empty(nv)  # x where the edges spanning this row's y cross it
    for j in range(nj):
        y = gy[j]
        n_cross = 0
        for a in range(nv):
            x1, y1 = verts[a, 0], verts[a, 1]
            b = a + 1 if a + 1 < nv else 0
            x2, y2 = verts[b, 0], verts[b, 1]
            if y1 != y2 and (y > y1) != (y > y2):
                crossing[n_cross] = x1 + (y - y1) * (x2 - x1) / (y2 - y1)
                n_cross += 1
        if n_cross == 0:
            continue
        for i in range(ni):
            x = gx[i]
            inside = False
            for c in range(n_cross):
                if x < crossing[c]:
                    inside = not inside
            if inside:
                out[j // ss, i // ss] += amp * (1.0 - np.exp(-speckle[j, i])) + base
    return out / (ss * ss)


def _render_units(
    cfg: CameraConfig, polygons_m: np.ndarray, poses: np.ndarray, tex: SpeckleTextures
) -> np.ndarray:
    """Noise-free, uniformly lit scene radiance (grey levels) as float64 [height, width]."""
    h, w, ss = cfg.height_px, cfg.width_px, cfg.supersample
    s = cfg.m_per_px
    sy = -1.0 if cfg.y_up else 1.0
    frame = np.full((h, w), cfg.background_level, dtype=np.float64)
    cents = area_centroids(polygons_m)
    amp = cfg.speckle_level - cfg.unit_level
    base = cfg.unit_level - cfg.background_level
    two_sig2 = 2.0 * tex.sigma_m**2
    # sub-pixel sample offsets inside one pixel, pixels (pixel centre at 0)
    sub = (np.arange(ss) + 0.5) / ss - 0.5
    for b in range(polygons_m.shape[0]):
        u, v, th = poses[b]
        if not np.all(np.isfinite(poses[b])):
            continue
        c, sn = np.cos(th), np.sin(th)
        rot = np.array([[c, -sn], [sn, c]])
        centre = cents[b] + (u, v)
        verts_rel = (polygons_m[b] - cents[b]) @ rot.T  # current orientation, centroid-relative
        vpx = sample_to_pixel(cfg, verts_rel + centre)
        c0 = max(int(np.floor(vpx[:, 0].min())) - 1, 0)
        c1 = min(int(np.ceil(vpx[:, 0].max())) + 2, w)
        r0 = max(int(np.floor(vpx[:, 1].min())) - 1, 0)
        r1 = min(int(np.ceil(vpx[:, 1].max())) + 2, h)
        if c1 <= c0 or r1 <= r0:
            continue
        cols = (np.arange(c0, c1)[:, None] + sub[None, :]).ravel()
        rows = (np.arange(r0, r1)[:, None] + sub[None, :]).ravel()
        # centroid-relative sample-frame coordinates of the sub-pixel grid, m
        gx = (cols - cfg.origin_px[0]) * s - centre[0]
        gy = sy * (rows - cfg.origin_px[1]) * s - centre[1]
        keep = tex.weights[b] > 0
        q = tex.centres_m[b, keep] @ rot.T  # blob centres in the current orientation
        e_col = np.exp(-((gx[None, :] - q[:, 0:1]) ** 2) / two_sig2)
        e_row = np.exp(-((gy[None, :] - q[:, 1:2]) ** 2) / two_sig2)
        frame[r0:r1, c0:c1] += _unit_block(
            e_row, e_col, gx, gy, np.ascontiguousarray(verts_rel), amp, base, ss
        )
    return frame


def lighting_field(cfg: CameraConfig) -> np.ndarray:
    """Relative illumination [height, width]: linear left-right gradient times vignetting."""
    col = np.arange(cfg.width_px) / max(cfg.width_px - 1, 1) - 0.5
    row = np.arange(cfg.height_px) / max(cfg.height_px - 1, 1) - 0.5
    r2 = (col[None, :] ** 2 + row[:, None] ** 2) / 0.5
    return (1.0 + cfg.lighting_gradient * col[None, :]) * (1.0 - cfg.vignetting * r2)


def render_frame(
    cfg: CameraConfig,
    polygons_m: np.ndarray,
    poses: np.ndarray,
    textures: SpeckleTextures,
    rng: np.random.Generator,
    *,
    motion_from: np.ndarray | None = None,
    occlusion: np.ndarray | None = None,
) -> np.ndarray:
    """Render one 8-bit frame.

    Args:
        cfg: camera configuration.
        polygons_m: [n_units, n_vertices, 2] reference outlines in the sample frame, m.
        poses: [n_units, 3] (u, v, theta): displacement of each unit's area centroid (m) and
            its counter-clockwise rotation about it (rad), relative to `polygons_m`, at the end
            of the exposure. A unit with a non-finite pose is not drawn.
        textures: speckle from `make_speckle_textures` for the same polygons.
        rng: random generator for the noise.
        motion_from: optional [n_units, 3] poses at the start of the exposure; the frame then
            averages `cfg.exposure_samples` renders at poses linearly spaced between the two
            (motion blur). The mid-exposure pose is the natural ground truth.
        occlusion: optional bool [height, width] mask of pixels hidden behind an occluder,
            painted at `cfg.occluder_level` (before optical blur and noise).

    Returns:
        uint8 [height, width] frame.
    """
    poly = np.asarray(polygons_m, dtype=np.float64)
    end = np.asarray(poses, dtype=np.float64)
    if poly.ndim != 3 or poly.shape[2] != 2 or end.shape != (poly.shape[0], 3):
        raise ValueError(f"polygons_m {poly.shape} / poses {end.shape} are not [n,nv,2] / [n,3]")
    if motion_from is None:
        img = _render_units(cfg, poly, end, textures)
    else:
        start = np.asarray(motion_from, dtype=np.float64)
        n = cfg.exposure_samples
        fracs = (np.arange(n) + 0.5) / n
        img = sum(_render_units(cfg, poly, start + f * (end - start), textures) for f in fracs) / n
    img = img * lighting_field(cfg)
    if occlusion is not None:
        img = np.where(np.asarray(occlusion, dtype=bool), cfg.occluder_level, img)
    if cfg.blur_sigma_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), cfg.blur_sigma_px, borderType=cv2.BORDER_REFLECT)
    if cfg.full_well > 0:
        electrons = np.clip(img, 0.0, None) / FULL_SCALE * cfg.full_well
        img = rng.poisson(electrons) * (FULL_SCALE / cfg.full_well)
    if cfg.noise_std > 0:
        img = img + rng.normal(0.0, cfg.noise_std * FULL_SCALE, size=img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


# frames the snapshot of the unloaded sample averages (`reference_image`): the reference's read
# noise is in every tracked pose alike (half of a pose's error variance with one frame);
# averaging 8 frames at rest brought the blurred optimised design's rotation p99 from 4.1 to
# 3.3 mrad (benchmarks/bench_dic_design.py)
REFERENCE_FRAMES = 8


def average_frames(frames: Sequence[np.ndarray]) -> np.ndarray:
    """Pixel mean of frames of one shape and integer dtype, rounded back to that dtype: the
    snapshot a camera takes by averaging frames of a scene at rest (its read noise shrinks as
    1 / sqrt(len(frames)); the rounding adds 1/sqrt(12) of a grey level)."""
    if len(frames) == 0:
        raise ValueError("no frames to average")
    first = np.asarray(frames[0])
    if any(np.shape(f) != first.shape or np.asarray(f).dtype != first.dtype for f in frames):
        raise ValueError("frames to average differ in shape or dtype")
    mean = np.mean(np.stack(frames), axis=0, dtype=np.float64)
    info = np.iinfo(first.dtype)
    return np.clip(np.rint(mean), info.min, info.max).astype(first.dtype)


def reference_image(
    cfg: CameraConfig, polygons_m: np.ndarray, seed: int, frames: int = REFERENCE_FRAMES
) -> np.ndarray:
    """The unloaded sample at rest, averaged over `frames` frames (uint8 [H, W]), with the
    speckle that a film drawing its textures first from `np.random.default_rng(seed)` shows.
    One frame gives exactly the single snapshot (the same noise draws)."""
    if frames < 1:
        raise ValueError(f"frames must be >= 1, got {frames}")
    rng = np.random.default_rng(seed)
    textures = make_speckle_textures(polygons_m, cfg, rng)
    still = np.zeros((np.shape(polygons_m)[0], 3))
    return average_frames(
        [render_frame(cfg, polygons_m, still, textures, rng) for _ in range(frames)]
    )
