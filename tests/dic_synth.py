"""Synthetic speckle scenes with exact ground truth for the DIC tests (helper, not a test)."""

from dataclasses import dataclass

import numpy as np

from hardware_sim.camera import (
    CameraConfig,
    make_speckle_textures,
    render_frame,
    square_lattice_polygons,
)
from tracking.calibration import Calibration


@dataclass(frozen=True)
class Scene:
    """A lattice of square units seen by the synthetic camera.

    Attributes:
        cfg: camera configuration. polygons_m: [n, 4, 2] outlines, m. textures: speckle.
        calib: the matching tracking calibration.
    """

    cfg: CameraConfig
    polygons_m: np.ndarray
    textures: object
    calib: Calibration

    @property
    def n(self) -> int:
        return self.polygons_m.shape[0]

    def px(self, pose_px: np.ndarray) -> np.ndarray:
        """(u px, v px, theta) -> (u m, v m, theta)."""
        return np.asarray(pose_px, float) * [self.cfg.m_per_px, self.cfg.m_per_px, 1.0]

    def render(self, poses, rng, **kw) -> np.ndarray:
        return render_frame(self.cfg, self.polygons_m, poses, self.textures, rng, **kw)


def make_scene(nx=3, ny=2, pitch_px=60, side_px=37, seed=0, **cam) -> Scene:
    """Square units of `side_px` on a `pitch_px` grid, 10 px border, speckle ~1 px blobs."""
    mpp = 0.015 / 40
    w, h = nx * pitch_px + 20, ny * pitch_px + 20
    opts = {"width_px": w, "height_px": h, "m_per_px": mpp, "origin_px": (10.0, h - 10.0),
            "speckle_sigma_m": 1.0 * mpp, "speckle_fill": 0.7, "unit_level": 20.0,
            "speckle_level": 230.0, "supersample": 3}
    opts.update(cam)
    cfg = CameraConfig(**opts)
    half = pitch_px * mpp / 2
    polys = square_lattice_polygons(nx, ny, pitch_px * mpp, side_px * mpp, (half, half))
    tex = make_speckle_textures(polys, cfg, np.random.default_rng(seed))
    cal = Calibration(fps=cfg.fps, m_per_px=mpp, origin_px=cfg.origin_px, y_up=cfg.y_up)
    return Scene(cfg, polys, tex, cal)


def errors_px(scene: Scene, q: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """RMS position error (px) and RMS rotation error (mrad) over finite estimates."""
    e = np.asarray(q) - np.asarray(truth)
    pos = np.sqrt(np.nanmean((e[..., :2] ** 2).sum(-1))) / scene.cfg.m_per_px
    rot = np.sqrt(np.nanmean(e[..., 2] ** 2)) * 1e3
    return float(pos), float(rot)
