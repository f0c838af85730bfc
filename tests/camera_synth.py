"""A known camera looking at a plane: renders calibration-target views and plane scenes (helper).

The camera is a pinhole with OpenCV's lens distortion (k1, k2, p1, p2, k3). Every raw pixel is
sampled at `ss x ss` points; each point is undistorted (the exact inverse of the model, by
iteration), its ray is met with the plane z = 0 of the plane frame, and the plane's picture
(a board image, or a square-on scene) is sampled there; the points of a pixel are averaged.
So a view differs from the truth only by the resampling of a picture much finer than the
camera's pixels.
"""

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class Camera:
    """Intrinsics K [3, 3] (px), distortion [5] (k1, k2, p1, p2, k3) and size (w, h) px."""

    K: np.ndarray
    dist: np.ndarray
    size: tuple[int, int]


def rotation(rx: float, ry: float, rz: float) -> np.ndarray:
    """Rotation matrix R = Rz @ Ry @ Rx (angles in rad)."""
    return cv2.Rodrigues(np.array([0.0, 0.0, rz]))[0] @ cv2.Rodrigues(
        np.array([0.0, ry, 0.0]))[0] @ cv2.Rodrigues(np.array([rx, 0.0, 0.0]))[0]


def look_at(rx: float, ry: float, rz: float, aim_m, at_cam_m) -> tuple[np.ndarray, np.ndarray]:
    """Plane -> camera pose (R, t) that turns the plane by (rx, ry, rz) and puts the plane
    point `aim_m` (X, Y) at `at_cam_m` (x, y, z) m in camera coordinates."""
    r = rotation(rx, ry, rz)
    t = np.asarray(at_cam_m, float) - r @ np.array([aim_m[0], aim_m[1], 0.0])
    return r, t


def ray_grid(cam: Camera, ss: int) -> np.ndarray:
    """Undistorted normalised coordinates [h * ss, w * ss, 2] of every sub-pixel sample.

    The distortion model is inverted by fixed-point iteration to 1e-13 (its own residual).
    """
    w, h = cam.size
    off = (np.arange(ss) + 0.5) / ss - 0.5
    cols = (np.arange(w)[:, None] + off[None, :]).ravel()
    rows = (np.arange(h)[:, None] + off[None, :]).ravel()
    cc, rr = np.meshgrid(cols, rows)
    k = cam.K
    yd = (rr - k[1, 2]) / k[1, 1]
    xd = (cc - k[0, 2] - k[0, 1] * yd) / k[0, 0]
    k1, k2, p1, p2, k3 = cam.dist
    x, y = xd.copy(), yd.copy()
    for _ in range(60):
        r2 = x * x + y * y
        rad = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xn = (xd - 2 * p1 * x * y - p2 * (r2 + 2 * x * x)) / rad
        yn = (yd - p1 * (r2 + 2 * y * y) - 2 * p2 * x * y) / rad
        done = max(np.abs(xn - x).max(), np.abs(yn - y).max()) < 1e-13
        x, y = xn, yn
        if done:
            break
    return np.stack([x, y], -1)


def plane_points(rays: np.ndarray, r: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Plane coordinates (X, Y) m [..., 2] met by normalised rays [..., 2] (pose R, t)."""
    m = np.column_stack([r[:, 0], r[:, 1], t])
    inv = np.linalg.inv(m)
    x = np.concatenate([rays, np.ones(rays.shape[:-1] + (1,))], -1)
    p = x @ inv.T
    return p[..., :2] / p[..., 2:3]


def view(picture: np.ndarray, to_px, rays: np.ndarray, r, t, ss: int, rng=None,
         noise: float = 0.0, border: float = 128.0, blur_px: float = 0.0) -> np.ndarray:
    """Render a raw uint8 view of a plane picture.

    Args:
        picture: float32 [H, W] image of the plane.
        to_px: plane (X, Y) m [..., 2] -> picture pixel (col, row) [..., 2].
        rays: `ray_grid` of the camera. r, t: plane -> camera pose. ss: its supersampling.
        rng, noise: Gaussian noise of this many grey levels.
        border: grey level outside the picture.
        blur_px: Gaussian optical blur, camera pixels (0: none).
    """
    px = to_px(plane_points(rays, r, t)).astype(np.float32)
    hi = cv2.remap(picture, px[..., 0], px[..., 1], cv2.INTER_LINEAR,
                   borderMode=cv2.BORDER_CONSTANT, borderValue=border)
    h, w = hi.shape[0] // ss, hi.shape[1] // ss
    img = hi.reshape(h, ss, w, ss).mean(axis=(1, 3))
    if blur_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_px)
    if noise > 0:
        img = img + rng.normal(0.0, noise, img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def charuco_picture(board, px_per_square: int, margin_px: int):
    """Board image (float32) and its map plane (X, Y) m -> picture (col, row)."""
    nx, ny = board.getChessboardSize()
    size = (nx * px_per_square + 2 * margin_px, ny * px_per_square + 2 * margin_px)
    img = board.generateImage(size, marginSize=margin_px, borderBits=1).astype(np.float32)
    s = px_per_square / board.getSquareLength()

    def to_px(xy):
        return xy * s + (margin_px - 0.5)

    return img, to_px


def project(cam: Camera, r, t, xy_m: np.ndarray) -> np.ndarray:
    """Plane points (X, Y) m [k, 2] -> distorted raw pixels [k, 2]."""
    obj = np.column_stack([xy_m, np.zeros(len(xy_m))]).astype(np.float64)
    px, _ = cv2.projectPoints(obj, cv2.Rodrigues(r)[0], t, cam.K, cam.dist)
    return px.reshape(-1, 2)
