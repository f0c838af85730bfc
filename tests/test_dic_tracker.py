"""DIC tracker on synthetic speckle frames with exact ground truth (small scenes)."""

from dataclasses import replace

import numpy as np
import pytest
from dic_synth import errors_px, make_scene

from tracking.dic import (
    DICConfig,
    DICTracker,
    FramePoses,
    SIGMA_SCALE,
    init_state,
    prepare_frame,
    track_frame,
)
from tracking.icgn import icgn
from tracking.kernels import bspline_coefficients, bspline_sample


def _run(scene, frames, cfg=None, reference=None):
    tr = DICTracker(scene.polygons_m, scene.calib, cfg or DICConfig())
    st = init_state(tr, frames[0] if reference is None else reference)
    out = []
    for f in frames:
        st, fp = track_frame(tr, st, f)
        out.append(fp)
    q = np.array([o.q for o in out])
    lost = np.array([o.lost for o in out])
    qual = np.array([o.quality for o in out])
    return q, lost, qual, st


def test_bspline_interpolant_is_exact_at_pixels_and_matches_scipy():
    from scipy import ndimage

    rng = np.random.default_rng(0)
    img = rng.random((40, 50)).astype(np.float32) * 200
    coef = bspline_coefficients(img)
    np.testing.assert_allclose(coef, ndimage.spline_filter(img.astype(float), 3, mode="mirror"),
                               atol=1e-3)
    r, c = np.mgrid[1:37, 1:47]
    np.testing.assert_allclose(bspline_sample(coef, c.ravel() * 1.0, r.ravel() * 1.0),
                               img[1:37, 1:47].ravel(), atol=1e-3)
    x, y = rng.uniform(2, 45, 200), rng.uniform(2, 35, 200)
    ref = ndimage.map_coordinates(ndimage.spline_filter(img.astype(float), 3, mode="mirror"),
                                  [y, x], order=3, prefilter=False)
    np.testing.assert_allclose(bspline_sample(coef, x, y), ref, atol=1e-3)
    assert np.isnan(bspline_sample(coef, np.array([0.5]), np.array([10.0])))[0]


@pytest.mark.parametrize("shift", [(0.0, 0.0), (0.5, 0.0), (0.25, -0.75), (2.3, 1.6)])
def test_subpixel_translation(shift):
    scene = make_scene(3, 2)
    rng = np.random.default_rng(1)
    truth = np.tile(scene.px([shift[0], shift[1], 0.0]), (scene.n, 1))
    frames = [scene.render(np.zeros((scene.n, 3)), rng), scene.render(truth, rng)]
    q, lost, qual, _ = _run(scene, frames)
    assert not lost.any()
    pos, rot = errors_px(scene, q[1], truth)
    assert pos < 0.01 and rot < 0.5
    assert np.all(qual[1] > 0.99)


def test_rotation_ramp_to_0p3_rad_with_reference_updates():
    scene = make_scene(2, 2)
    rng = np.random.default_rng(2)
    n_t = 16
    theta = np.linspace(0, 0.3, n_t)
    truth = np.zeros((n_t, scene.n, 3))
    truth[:, :, 2] = theta[:, None] * np.array([1, -1, 1, -1])
    truth[:, :, 0] = np.linspace(0, 2.5, n_t)[:, None] * scene.cfg.m_per_px
    frames = [scene.render(p, rng) for p in truth]
    q, lost, _, st = _run(scene, frames)
    assert not lost.any()
    pos, rot = errors_px(scene, q, truth)
    assert pos < 0.01 and rot < 0.5
    assert np.all(np.abs(st.ref_alpha) > 0.15)  # references were refreshed on the way
    # refreshed in place in the tracker's own arrays, never in the reference image's subsets
    # (the drift-free check registers against those), which stay as first extracted
    tr = DICTracker(scene.polygons_m, scene.calib, DICConfig())
    fresh = init_state(tr, frames[0])
    assert st.refs_own and st.refs.ft is not st.refs0.ft
    for name in fresh.refs0.__slots__:
        np.testing.assert_array_equal(getattr(st.refs0, name), getattr(fresh.refs0, name))
        np.testing.assert_array_equal(getattr(st.pieces0.refs, name),
                                      getattr(fresh.pieces0.refs, name))
    assert not np.array_equal(st.refs.ft, st.refs0.ft)


def test_noise_blur_shot_and_uneven_lighting():
    scene = make_scene(3, 2, noise_std=0.02, full_well=4000.0, blur_sigma_px=0.7,
                       lighting_gradient=0.3, vignetting=0.2)
    rng = np.random.default_rng(3)
    n_t = 8
    truth = np.zeros((n_t, scene.n, 3))
    k = np.arange(n_t)[:, None]
    truth[..., 0] = 0.4 * k * scene.cfg.m_per_px  # moves through the lighting gradient
    truth[..., 1] = -0.3 * k * scene.cfg.m_per_px
    truth[..., 2] = 0.01 * k
    frames = [scene.render(p, rng) for p in truth]
    q, lost, qual, _ = _run(scene, frames)
    assert not lost.any()
    pos, rot = errors_px(scene, q[1:], truth[1:])
    assert pos < 0.03 and rot < 1.5
    assert np.all(qual[1:] > 0.9)


def test_occluded_unit_is_flagged_lost_then_recovers():
    scene = make_scene(3, 2)
    rng = np.random.default_rng(4)
    n_t = 10
    truth = np.zeros((n_t, scene.n, 3))
    truth[..., 0] = 0.3 * np.arange(n_t)[:, None] * scene.cfg.m_per_px
    c = scene.calib.sample_to_px(scene.polygons_m[4].mean(axis=0))
    occ = np.zeros((scene.cfg.height_px, scene.cfg.width_px), bool)
    occ[int(c[1]) - 25 : int(c[1]) + 25, int(c[0]) - 25 : int(c[0]) + 25] = True
    frames = [scene.render(p, rng, occlusion=occ if 4 <= k < 7 else None)
              for k, p in enumerate(truth)]
    q, lost, _, _ = _run(scene, frames)
    assert lost[4:7, 4].all() and np.isnan(q[4:7, 4]).all()
    others = np.delete(np.arange(scene.n), 4)
    assert not lost[:, others].any()
    assert not lost[7:, 4].any()  # re-acquired once visible again
    pos, rot = errors_px(scene, q[7:, 4], truth[7:, 4])
    assert pos < 0.01 and rot < 0.5


def test_unit_leaving_the_field_is_lost_not_guessed():
    scene = make_scene(3, 1)
    rng = np.random.default_rng(5)
    n_t = 12
    truth = np.zeros((n_t, scene.n, 3))
    truth[:, 0, 0] = -np.linspace(0, 35, n_t) * scene.cfg.m_per_px  # unit 0 slides out left
    frames = [scene.render(p, rng) for p in truth]
    q, lost, _, _ = _run(scene, frames)
    assert lost[-1, 0] and np.isnan(q[-1, 0]).all()
    visible = ~lost[:, 0]
    assert visible[:3].all()
    pos, _ = errors_px(scene, q[visible, 0], truth[visible, 0])
    assert pos < 0.01
    assert not lost[:, 1:].any()


def test_blank_and_corrupt_frames_are_flagged_not_fatal():
    scene = make_scene(2, 2)
    rng = np.random.default_rng(6)
    truth = [np.tile(scene.px([0.2 * k, 0.1 * k, 0.0]), (scene.n, 1)) for k in range(6)]
    frames = [scene.render(p, rng) for p in truth]
    frames[2] = np.zeros_like(frames[2])  # blank
    frames[3] = frames[3][:-5]  # truncated
    frames[4] = np.full(frames[4].shape, np.nan)  # garbage
    q, lost, _, _ = _run(scene, frames)
    assert lost[2:5].all() and np.isnan(q[2:5]).all()
    assert not lost[[0, 1, 5]].any()
    pos, _ = errors_px(scene, q[5], truth[5])
    assert pos < 0.01


def test_units_outside_the_reference_frame_are_always_lost():
    scene = make_scene(3, 1)
    polys = scene.polygons_m.copy()
    polys[2] += [0.05, 0.0]  # far right of the image
    tr = DICTracker(polys, scene.calib)
    f = scene.render(np.zeros((3, 3)), np.random.default_rng(0))
    st = init_state(tr, f)
    st, fp = track_frame(tr, st, f)
    assert isinstance(fp, FramePoses)
    np.testing.assert_array_equal(fp.lost, [False, False, True])
    assert np.isnan(fp.q[2]).all()


def test_icgn_recovers_large_rotation_from_a_nearby_start():
    scene = make_scene(2, 1)
    rng = np.random.default_rng(7)
    tr = DICTracker(scene.polygons_m, scene.calib)
    st = init_state(tr, scene.render(np.zeros((2, 3)), rng))
    truth = np.array([[0, 0, 0.3], [0, 0, -0.3]])
    prep = prepare_frame(tr, scene.render(truth, rng))
    r = icgn(prep.coef, st.refs, np.arange(2), -truth[:, 2] * 0.9, np.zeros((2, 2)))
    assert r.converged.all() and r.inside.all()
    np.testing.assert_allclose(r.alpha, -truth[:, 2], atol=5e-4)


def _precompressed(scene, closing_px: float, turn: float) -> np.ndarray:
    """Poses [n, 3] of a sample closed by `closing_px` (top and bottom rows each move half of it
    toward the centre, rows between in proportion), units turning +-`turn` in a checkerboard
    (the rotating-square pattern) and the whole sample shifted 1.3 px to the right."""
    c = scene.polygons_m.mean(axis=1)
    y = (c[:, 1] - c[:, 1].mean()) / np.ptp(c[:, 1])  # -1/2 .. 1/2
    ny = len(np.unique(np.round(c[:, 1], 9)))
    col = np.round((c[:, 0] - c[:, 0].min()) / np.ptp(c[:, 0]) * (scene.n // ny - 1))
    row = np.round((y + 0.5) * (ny - 1))
    q = np.zeros((scene.n, 3))
    q[:, 0] = 1.3 * scene.cfg.m_per_px
    q[:, 1] = -y * closing_px * scene.cfg.m_per_px
    q[:, 2] = turn * np.where((col + row) % 2 == 0, 1.0, -1.0)
    return q


@pytest.mark.parametrize("closing_px, turn", [(14.0, 0.15), (30.0, 0.3)])
def test_a_precompressed_first_frame_is_found_against_the_unloaded_reference(closing_px, turn):
    # the rig's procedure: the reference image shows the sample unloaded, the first frame
    # pre-compressed (units moved up to closing/2 px and turned): poses must be measured from the
    # unloaded outlines, not assumed zero in the first frame (the old behaviour, wrong by the
    # whole pre-compression and, with templates cut at the wrong place, in the motion after it)
    scene = make_scene(4, 3)
    rng = np.random.default_rng(7)
    q0 = _precompressed(scene, closing_px, turn)
    reference = scene.render(np.zeros((scene.n, 3)), rng)
    step = np.zeros((scene.n, 3))
    step[:, 0] = 0.4 * scene.cfg.m_per_px
    truth = np.array([q0, q0 + step, q0 + 2 * step])
    q, lost, qual, _ = _run(scene, [scene.render(p, rng) for p in truth], reference=reference)
    assert not lost.any() and np.all(qual > 0.99)
    pos, rot = errors_px(scene, q, truth)
    assert pos < 0.01 and rot < 0.5, (pos, rot)


def _sliver_scene(width_px: float = 8.0, seed: int = 1, **cam):
    """4 x 3 units, every other one a sliver `width_px` wide (8: no search template fits inside
    it), its speckle drawn with `seed`."""
    from hardware_sim.camera import make_speckle_textures

    base = make_scene(4, 3, **cam)
    polys = base.polygons_m.copy()
    slim = np.arange(base.n) % 2 == 1
    c = polys[slim].mean(axis=1, keepdims=True)
    polys[slim] = c + (polys[slim] - c) * np.array([width_px / 37.0, 1.0])
    tex = make_speckle_textures(polys, base.cfg, np.random.default_rng(seed))
    return type(base)(base.cfg, polys, tex, base.calib), slim


def test_units_too_slender_for_a_search_template_start_from_their_neighbours():
    from tracking.dic import acquire_frame
    from tracking.search import MIN_TEMPLATE_HALF

    scene, slim = _sliver_scene()
    rng = np.random.default_rng(8)
    q0 = _precompressed(scene, 10.0, 0.0)
    q0[:, 2] = 0.05
    reference = scene.render(np.zeros((scene.n, 3)), rng)
    frame = scene.render(q0, rng)
    tr = DICTracker(scene.polygons_m, scene.calib, DICConfig(margin_px=1.5, min_points=16))
    st = init_state(tr, reference)
    assert np.all(st.refs.tpl_half[slim] < MIN_TEMPLATE_HALF) and st.refs.count[slim].min() > 0
    assert not acquire_frame(tr, st, prepare_frame(tr, frame)).lost.any()
    q, lost, qual, _ = _run(scene, [frame], DICConfig(margin_px=1.5, min_points=16), reference)
    assert not lost.any()
    pos, rot = errors_px(scene, q[0], q0)
    assert pos < 0.02 and rot < 2.0, (pos, rot)


@pytest.mark.parametrize("noise", [0.01, 0.03])
def test_every_pose_carries_a_standard_error_that_covers_its_true_error(noise):
    # the noise part, calibrated against truth (tracking.dic.SIGMA_SCALE, NOISE_AREA_SHARE for
    # the default prefilter): about 95 % of the true errors lie within 2 sigma; measured
    # 0.955-0.99 per component over these sharp scenes without the systematic floor, so
    # [0.85, 0.995] fails a sigma that is 1.4x too small or 1.6x too large
    scene = make_scene(4, 3, noise_std=noise)
    rng = np.random.default_rng(11)
    n_t = 25
    truth = np.zeros((n_t, scene.n, 3))
    truth[:, :, 0] = (0.37 * np.arange(n_t))[:, None] * scene.cfg.m_per_px
    truth[:, :, 1] = (0.21 * np.arange(n_t))[:, None] * scene.cfg.m_per_px
    truth[:, :, 2] = (0.004 * np.arange(n_t))[:, None]
    frames = [scene.render(p, rng) for p in truth]
    tr = DICTracker(scene.polygons_m, scene.calib,
                    DICConfig(sigma_floor_px=0.0, sigma_blur_share=0.0))  # frames not blurred
    floored = DICTracker(scene.polygons_m, scene.calib,
                         DICConfig(sigma_floor_px=0.02, sigma_blur_share=0.0))
    st, st_f = init_state(tr, frames[0]), init_state(floored, frames[0])
    err, sig = [], []
    for f, q in zip(frames[1:], truth[1:], strict=True):
        st, fp = track_frame(tr, st, f)
        assert not fp.lost.any() and np.all(fp.sigma > 0)
        err.append(fp.q - q)
        sig.append(fp.sigma)
        # the floor adds in quadrature (the same poses: it changes no registration)
        st_f, fpf = track_frame(floored, st_f, f)
        np.testing.assert_array_equal(fpf.q, fp.q)
        floor_m = SIGMA_SCALE * 0.02 * scene.cfg.m_per_px
        assert np.all(fpf.sigma[:, :2] >= np.hypot(fp.sigma[:, :2], floor_m) * (1 - 1e-9))
    z = np.abs(np.array(err)) / np.array(sig)
    within = np.mean(z < 2.0, axis=(0, 1))
    assert np.all((within > 0.85) & (within < 0.995)), within
    # the error it states grows with the noise: 3x the noise, about 3x sigma
    px = np.mean(np.array(sig)[..., :2]) / scene.cfg.m_per_px
    assert (0.002 < px < 0.005) if noise == 0.01 else (0.006 < px < 0.014), px


def test_standard_errors_travel_in_the_trajectory_file(tmp_path):
    from metarig.trajectory import Trajectory

    q = np.random.default_rng(0).normal(size=(4, 3, 3))
    sigma = np.abs(q) * 1e-3
    t = Trajectory.from_positions(np.arange(4) * 1e-3, q, sigma=sigma)
    back = Trajectory.load_npz(t.save_npz(tmp_path / "t.npz"))
    np.testing.assert_array_equal(back.sigma, sigma)
    assert back.window(1, 3).sigma.shape == (2, 3, 3)
    assert Trajectory.load_npz(Trajectory.from_positions(np.arange(4.0), q).save_npz(
        tmp_path / "old.npz")).sigma is None  # files without it still read
    with pytest.raises(ValueError, match="sigma shape"):
        Trajectory.from_positions(np.arange(4.0), q, sigma=sigma[:, :2])


def test_a_reference_refreshed_at_a_wrong_pose_does_not_carry_its_error_on():
    # a reference refreshed during fast blurred motion can be cut at a pose some 30 mrad off;
    # every later frame registers against it at a high correlation, and without a check the
    # error stays in every pose. The reference image's own subsets catch it.
    scene = make_scene(2, 2)
    rng = np.random.default_rng(2)
    n_t = 16
    truth = np.zeros((n_t, scene.n, 3))
    truth[:, :, 2] = np.linspace(0, 0.3, n_t)[:, None] * np.array([1, -1, 1, -1])
    frames = [scene.render(p, rng) for p in truth]
    tr = DICTracker(scene.polygons_m, scene.calib, DICConfig())
    for check in (True, False):
        st = init_state(tr, frames[0])
        st = st if check else replace(st, refs0=None)
        for k, f in enumerate(frames):
            st, fp = track_frame(tr, st, f)
            if k == 12:  # references refreshed (rotated > 0.2 rad): poison unit 1's
                assert st.ref_alpha[1] != 0.0
                st = replace(st, ref_alpha=st.ref_alpha + np.array([0.0, 0.03, 0.0, 0.0]))
        err = np.abs(fp.q[:, 2] - truth[-1, :, 2])
        if check:
            assert not fp.lost.any() and err.max() < 1e-3, err
        else:  # the failure the check prevents: 30 mrad off at a correlation above 0.99
            assert err[1] > 0.02 and fp.quality[1] > 0.99


def test_a_lost_sliver_is_found_again_from_its_neighbours():
    # a template search cannot find a sliver (no template fits in it): once lost (here
    # occluded for three frames) it used to stay lost for good
    scene, _ = _sliver_scene()
    rng = np.random.default_rng(9)
    n_t = 10
    truth = np.zeros((n_t, scene.n, 3))
    truth[:, :, 0] = (0.6 * np.arange(n_t))[:, None] * scene.cfg.m_per_px
    truth[:, :, 2] = (0.004 * np.arange(n_t))[:, None]
    c = scene.calib.sample_to_px(scene.polygons_m[5].mean(axis=0))
    occ = np.zeros((scene.cfg.height_px, scene.cfg.width_px), bool)
    occ[int(c[1]) - 25 : int(c[1]) + 25, int(c[0]) - 8 : int(c[0]) + 8] = True
    frames = [scene.render(p, rng, occlusion=occ if 3 <= k < 6 else None)
              for k, p in enumerate(truth)]
    q, lost, _, _ = _run(scene, frames, DICConfig(margin_px=1.5, min_points=16))
    assert lost[3:6, 5].all() and not lost[6:, 5].any()
    pos, rot = errors_px(scene, q[6:, 5], truth[6:, 5])
    assert pos < 0.02 and rot < 2.0, (pos, rot)


def test_blurred_fast_turning_slivers_are_never_wrong_without_a_flag():
    # the motion the optimised designs show: slivers swinging +-0.3 rad (up to 0.12 rad per
    # frame) against their neighbours while the sample sways +-10 px, blurred over half a frame
    # (the rig camera's exposure), 1 % read noise; the truth is the pose at the middle of each
    # exposure, as the simulated camera stamps it. In frames 12-14 the upper 40 % of sliver 5
    # is seen 2.5 px across from the rest of it (an end bent, or overlapped by a neighbour's
    # speckle): no rigid pose fits it, and whole-subset IC-GN settles ~100 mrad off at ZNCC
    # 0.94, a pose only the check by the unit's own pieces rejects. Every pose not flagged lost
    # must be within 0.5 px and 10 mrad (measured: none lost but sliver 5 in frames 12-14,
    # largest errors 0.044 px and 3.0 mrad)
    scene, slim = _sliver_scene(noise_std=0.01)
    rng = np.random.default_rng(12)
    k = np.arange(30)
    truth = np.zeros((k.size, scene.n, 3))
    truth[:, :, 0] = (10.0 * np.sin(np.pi * k / 10))[:, None] * scene.cfg.m_per_px
    truth[:, :, 2] = (0.3 * np.sin(np.pi * k / 8))[:, None] * np.where(slim, 1.0, -1.0)
    start = np.r_[truth[:1], truth[:-1]]  # each exposure: half a frame up to the frame's pose
    start = truth - 0.5 * (truth - start)
    frames = []
    for j, (q, q0) in enumerate(zip(truth, start, strict=True)):
        f = scene.render(q, rng, motion_from=q0)
        if 12 <= j < 15:
            bent = np.zeros_like(q)
            bent[5, 0] = 2.5 * scene.cfg.m_per_px
            g = scene.render(q + bent, rng, motion_from=q0 + bent)
            c = np.rint(scene.calib.sample_to_px(scene.polygons_m[5].mean(axis=0) + q[5, :2]))
            rows, cols = slice(int(c[1]) - 20, int(c[1]) - 4), slice(int(c[0]) - 10,
                                                                    int(c[0]) + 11)
            f[rows, cols] = g[rows, cols]
        frames.append(f)
    cfg = DICConfig(margin_px=1.5, min_points=16)
    for check in (True, False):
        q, lost, _, _ = _run(scene, frames, cfg if check else replace(cfg, check_pieces=0))
        e = q - 0.5 * (truth + start)
        pos = np.hypot(e[..., 0], e[..., 1]) / scene.cfg.m_per_px
        wrong = ~lost & ((pos > 0.5) | (np.abs(e[..., 2]) > 0.01))
        if check:
            assert not wrong.any(), np.argwhere(wrong)
            assert lost[12:15, 5].all() and lost.mean() < 0.02, np.argwhere(lost)
        else:  # the failure the check prevents: sliver 5 reported wrong, unflagged
            assert wrong[12:15, 5].all()


def test_slivers_turn_more_precisely_at_the_small_unit_margin():
    # a sliver's rotation is measured by its few pixel rows along its length: the small-unit
    # margin (tracking.dic_config.SMALL_UNIT_MARGIN_PX, 1.0 px) keeps more of them than 1.5 px,
    # on frames whose pixels integrate their light (4 x 4 points: 2 x 2 alias the outline's
    # edge). Slivers 5 and 6 px wide turning +-0.1 rad, 1 % read noise, 3 speckle draws each:
    # measured RMS rotation error 0.85 of that at 1.5 px over all (0.68-0.98 per draw), no
    # pose lost or wrong at either margin
    from tracking.dic_config import SMALL_UNIT_MARGIN_PX

    sq = {SMALL_UNIT_MARGIN_PX: [], 1.5: []}
    k = np.arange(30)
    for width in (5.0, 6.0):
        for seed in (0, 1, 2):
            scene, slim = _sliver_scene(width, seed, noise_std=0.01, supersample=4)
            rng = np.random.default_rng(100 + seed)
            truth = np.zeros((k.size, scene.n, 3))
            truth[:, :, 0] = (3.0 * np.sin(np.pi * k / 10))[:, None] * scene.cfg.m_per_px
            truth[:, :, 2] = (0.1 * np.sin(np.pi * k / 8))[:, None] * np.where(slim, 1.0, -1.0)
            reference = scene.render(np.zeros((scene.n, 3)), rng)
            frames = [scene.render(q, rng) for q in truth]
            for margin, errs in sq.items():
                q, lost, _, _ = _run(scene, frames, DICConfig(margin_px=margin, min_points=16),
                                     reference)
                e = q - truth
                pos = np.hypot(e[..., 0], e[..., 1]) / scene.cfg.m_per_px
                assert not lost.any() and pos.max() < 0.5 and np.abs(e[..., 2]).max() < 0.01
                errs.append(e[:, slim, 2] ** 2)
    rms = {m: np.sqrt(np.mean(v)) for m, v in sq.items()}
    assert rms[SMALL_UNIT_MARGIN_PX] < 0.93 * rms[1.5], rms


def test_a_units_pieces_partition_its_subset_and_their_rigid_fit_is_exact():
    from tracking.checks import rigid_fit, split_refs

    scene, slim = _sliver_scene()
    st = init_state(DICTracker(scene.polygons_m, scene.calib,
                               DICConfig(margin_px=1.5, min_points=16)),
                    scene.render(np.zeros((scene.n, 3)), np.random.default_rng(0)))
    for parts in (2, 3):
        pieces = split_refs(st.refs, parts)
        idx = pieces.index(np.arange(scene.n))
        count = pieces.refs.count[idx]
        np.testing.assert_array_equal(count.sum(axis=1), st.refs.count)
        assert np.all(count.max(axis=1) - count.min(axis=1) <= 1)  # equal shares
        # the pieces' centroids average to the subset's, and lie along its long axis
        mean = np.stack([(st.refs.dx * st.refs.mask).sum(1), (st.refs.dy * st.refs.mask).sum(1)],
                        axis=1) / st.refs.count[:, None]
        off = pieces.offset[idx]
        np.testing.assert_allclose((off * count[..., None]).sum(1) / st.refs.count[:, None], mean,
                                   atol=1e-4)
        along = np.abs(off[slim] - mean[slim, None, :])
        assert np.all(along[..., 1] > 4 * along[..., 0])  # slivers are long in rows
    # a rigid motion is recovered exactly from points it carried
    rng = np.random.default_rng(3)
    offset = rng.normal(size=(5, 3, 2)) * 8
    alpha, w = rng.uniform(-0.3, 0.3, 5), rng.normal(size=(5, 2))
    c, s = np.cos(alpha)[:, None], np.sin(alpha)[:, None]
    carried = np.stack([c * offset[..., 0] - s * offset[..., 1],
                        s * offset[..., 0] + c * offset[..., 1]], -1) + w[:, None, :]
    a, ww = rigid_fit(offset, carried - offset)
    np.testing.assert_allclose(a, alpha, atol=1e-12)
    np.testing.assert_allclose(ww, w, atol=1e-12)
