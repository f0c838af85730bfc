"""Synthetic camera: exact analytic rendering, pixel integration, optics and noise options."""

import numpy as np
import pytest

from hardware_sim.camera import (
    CameraConfig,
    SpeckleTextures,
    average_frames,
    lighting_field,
    make_speckle_textures,
    reference_image,
    render_frame,
    sample_to_pixel,
    square_lattice_polygons,
)
from metarig.polygon import area_centroids

MPP = 0.015 / 40


def _one_unit(ss=1, **kw):
    cfg = CameraConfig(width_px=80, height_px=70, m_per_px=MPP, origin_px=(10.0, 60.0),
                       speckle_sigma_m=1.2 * MPP, supersample=ss, **kw)
    poly = square_lattice_polygons(1, 1, 0.0, 36 * MPP, (30 * MPP, 25 * MPP))
    tex = make_speckle_textures(poly, cfg, np.random.default_rng(3))
    return cfg, poly, tex


def _analytic(cfg, poly, tex, pose, col, row):
    """Brute-force scene radiance at pixel-centre points (no supersampling)."""
    u, v, th = pose
    c = area_centroids(poly)[0] + (u, v)
    x = (col - cfg.origin_px[0]) * cfg.m_per_px - c[0]
    y = (cfg.origin_px[1] - row) * cfg.m_per_px - c[1]
    ct, st = np.cos(th), np.sin(th)
    bx, by = ct * x + st * y, -st * x + ct * y  # body coordinates
    s = np.zeros_like(x)
    for p in tex.centres_m[0][tex.weights[0] > 0]:
        s += np.exp(-((bx - p[0]) ** 2 + (by - p[1]) ** 2) / (2 * tex.sigma_m**2))
    return cfg.unit_level + (cfg.speckle_level - cfg.unit_level) * (1 - np.exp(-s)), bx, by


@pytest.mark.parametrize("pose", [(0.0, 0.0, 0.0), (2.3 * MPP, -1.7 * MPP, 0.21)])
def test_render_matches_analytic_function(pose):
    cfg, poly, tex = _one_unit(ss=1)
    frame = render_frame(cfg, poly, np.array([pose]), tex, np.random.default_rng(0))
    row, col = np.mgrid[: cfg.height_px, : cfg.width_px].astype(float)
    ref, bx, by = _analytic(cfg, poly, tex, pose, col, row)
    inner = (np.abs(bx) < 15 * MPP) & (np.abs(by) < 15 * MPP)
    assert inner.sum() > 500
    np.testing.assert_array_equal(frame[inner], np.clip(np.rint(ref[inner]), 0, 255))
    assert np.all(frame[~(np.abs(bx) < 19 * MPP) | ~(np.abs(by) < 19 * MPP)]
                  == cfg.background_level)


def test_pixel_integration_is_shift_exact():
    """Whole-pixel moves shift the integrated image exactly; sub-pixel moves change it."""
    cfg, poly, tex = _one_unit(ss=4)
    rng = np.random.default_rng(0)
    f0 = render_frame(cfg, poly, np.zeros((1, 3)), tex, rng).astype(int)
    f1 = render_frame(cfg, poly, np.array([[3 * MPP, 2 * MPP, 0.0]]), tex, rng).astype(int)
    np.testing.assert_array_equal(f1[5:-5, 8:-5], f0[7:-3, 5:-8])
    f2 = render_frame(cfg, poly, np.array([[0.5 * MPP, 0, 0.0]]), tex, rng).astype(int)
    assert np.abs(f2 - f0).max() > 10


def test_supersampling_converges():
    cfg1, poly, tex = _one_unit(ss=6)
    cfg2 = CameraConfig(**{**{f: getattr(cfg1, f) for f in cfg1.__slots__}, "supersample": 12})
    pose = np.array([[0.3 * MPP, 0.1 * MPP, 0.1]])
    a = render_frame(cfg1, poly, pose, tex, np.random.default_rng(0)).astype(int)
    b = render_frame(cfg2, poly, pose, tex, np.random.default_rng(0)).astype(int)
    row, col = np.mgrid[: cfg1.height_px, : cfg1.width_px].astype(float)
    _, bx, by = _analytic(cfg1, poly, tex, pose[0], col, row)
    inner = (np.abs(bx) < 17 * MPP) & (np.abs(by) < 17 * MPP)
    assert np.abs(a - b)[inner].max() <= 1  # smooth interior: converged to rounding
    assert np.abs(a - b).mean() < 0.1  # edge pixels: coverage resolved to 1/36 vs 1/144


def test_textures_seeded_and_sized():
    cfg, poly, _ = _one_unit()
    t1 = make_speckle_textures(poly, cfg, np.random.default_rng(5))
    t2 = make_speckle_textures(poly, cfg, np.random.default_rng(5))
    np.testing.assert_array_equal(t1.centres_m, t2.centres_m)
    n = t1.weights.sum()
    area = (36 * MPP + 6 * cfg.speckle_sigma_m) ** 2
    expect = cfg.speckle_fill * area / (2 * np.pi * cfg.speckle_sigma_m**2)
    assert abs(n - expect) < 5 * np.sqrt(expect)
    assert isinstance(t1, SpeckleTextures)


def test_noise_blur_lighting_occlusion_options():
    rng = np.random.default_rng(1)
    cfg, poly, tex = _one_unit(ss=2)
    pose = np.zeros((1, 3))
    clean = render_frame(cfg, poly, pose, tex, rng).astype(float)
    noisy_cfg = CameraConfig(**{**{f: getattr(cfg, f) for f in cfg.__slots__},
                                "noise_std": 0.02})
    noisy = render_frame(noisy_cfg, poly, pose, tex, rng).astype(float)
    # background region: flat, so the difference is the read noise (2 % of 255)
    assert abs(np.std(noisy[:5] - clean[:5]) - 0.02 * 255) < 0.6
    shot_cfg = CameraConfig(**{**{f: getattr(cfg, f) for f in cfg.__slots__},
                               "full_well": 2000.0})
    shot = render_frame(shot_cfg, poly, pose, tex, rng).astype(float)
    # shot noise variance = I * 255 / full_well
    assert abs(np.var(shot[:5] - clean[:5]) - cfg.background_level * 255 / 2000) < 0.8
    blur_cfg = CameraConfig(**{**{f: getattr(cfg, f) for f in cfg.__slots__},
                               "blur_sigma_px": 1.0})
    blurred = render_frame(blur_cfg, poly, pose, tex, rng).astype(float)
    assert np.abs(np.diff(blurred, axis=1)).mean() < 0.8 * np.abs(np.diff(clean, axis=1)).mean()
    lit_cfg = CameraConfig(**{**{f: getattr(cfg, f) for f in cfg.__slots__},
                              "lighting_gradient": 0.4})
    field = lighting_field(lit_cfg)
    assert field[0, -1] / field[0, 0] == pytest.approx(1.2 / 0.8)
    occ = np.zeros((cfg.height_px, cfg.width_px), bool)
    occ[20:40, 20:40] = True
    hidden = render_frame(cfg, poly, pose, tex, rng, occlusion=occ)
    assert np.all(hidden[occ] == cfg.occluder_level)
    np.testing.assert_array_equal(hidden[~occ], clean[~occ])


def test_motion_blur_and_hidden_units():
    cfg, poly, tex = _one_unit(ss=2)
    rng = np.random.default_rng(0)
    pose = np.array([[1 * MPP, 0.0, 0.05]])
    sharp = render_frame(cfg, poly, pose, tex, rng)
    same = render_frame(cfg, poly, pose, tex, rng, motion_from=pose)
    assert np.abs(sharp.astype(int) - same.astype(int)).max() <= 1
    smeared = render_frame(cfg, poly, pose, tex, rng, motion_from=pose - [[4 * MPP, 0, 0]])
    assert np.abs(np.diff(smeared.astype(float), axis=1)).mean() < \
        np.abs(np.diff(sharp.astype(float), axis=1)).mean()
    gone = render_frame(cfg, poly, np.full((1, 3), np.nan), tex, rng)
    assert np.all(gone == cfg.background_level)


def test_pixel_map_and_config_validation():
    cfg = CameraConfig(origin_px=(5.0, 100.0), m_per_px=1e-3, y_up=True)
    np.testing.assert_allclose(sample_to_pixel(cfg, [[0.01, 0.02]]), [[15.0, 80.0]])
    cfg_down = CameraConfig(origin_px=(5.0, 100.0), m_per_px=1e-3, y_up=False)
    np.testing.assert_allclose(sample_to_pixel(cfg_down, [[0.01, 0.02]]), [[15.0, 120.0]])
    with pytest.raises(ValueError):
        CameraConfig(m_per_px=0.0)
    with pytest.raises(ValueError):
        CameraConfig(supersample=0)
    with pytest.raises(ValueError):
        render_frame(cfg, np.zeros((2, 4, 2)), np.zeros((3, 3)), None, None)


def test_lattice_frame_renders_fast_enough():
    """640x480, 24x16 units: the rig's default camera renders well above 1 frame/s."""
    import time

    cfg = CameraConfig(speckle_sigma_m=6e-4)
    polys = square_lattice_polygons(24, 16, 0.015, 0.013, (0.0075, 0.0075))
    tex = make_speckle_textures(polys, cfg, np.random.default_rng(0))
    rng = np.random.default_rng(0)
    render_frame(cfg, polys[:2], np.zeros((2, 3)), SpeckleTextures(
        tex.centres_m[:2], tex.weights[:2], tex.sigma_m), rng)  # compile
    t0 = time.perf_counter()
    frame = render_frame(cfg, polys, np.zeros((384, 3)), tex, rng)
    assert frame.shape == (480, 640) and frame.dtype == np.uint8
    assert time.perf_counter() - t0 < 5.0
    px = sample_to_pixel(cfg, area_centroids(polys))
    assert px[:, 0].min() > 0 and px[:, 0].max() < 640 and px[:, 1].min() > 0


def test_the_reference_snapshot_averages_frames_at_rest():
    # the snapshot of the unloaded sample: its read noise falls as 1 / sqrt(frames) (plus the
    # rounding back to 8 bits, 1/sqrt(12) grey level); one frame is the single snapshot itself
    cfg, poly, tex = _one_unit(ss=2)
    noisy = CameraConfig(**{**{f: getattr(cfg, f) for f in cfg.__slots__}, "noise_std": 0.02})
    clean = reference_image(cfg, poly, seed=5, frames=1).astype(float)
    rng = np.random.default_rng(5)
    single = render_frame(noisy, poly, np.zeros((1, 3)),
                          make_speckle_textures(poly, noisy, rng), rng)
    np.testing.assert_array_equal(reference_image(noisy, poly, seed=5, frames=1), single)
    for n in (4, 16):
        ref = reference_image(noisy, poly, seed=5, frames=n)
        assert ref.dtype == np.uint8 and ref.shape == clean.shape
        expected = np.sqrt((0.02 * 255) ** 2 / n + 1 / 12)
        assert abs(np.std(ref[:5] - clean[:5]) / expected - 1) < 0.15  # flat background rows
    frames = [np.full((2, 3), v, np.uint16) for v in (1000, 1001, 1003)]
    avg = average_frames(frames)
    assert avg.dtype == np.uint16 and np.all(avg == 1001)  # 1001.33 rounded
    with pytest.raises(ValueError):
        average_frames([frames[0], frames[0].astype(np.uint8)])
