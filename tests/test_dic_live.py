"""Live preview logic (no ROS): newest-frame slot, never blocking, decimation, reset."""

import threading
import time

import numpy as np
import pytest
from dic_synth import errors_px, make_scene

from metarig.polygon import area_centroids
from metarig.trajectory import to_absolute
from ros_nodes.dic_params import DICNodeConfig
from tracking.dic import DICTracker
from tracking.live import LivePreview


def _wait(cond, timeout_s=20.0):
    deadline = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.005)


def test_offer_never_blocks_and_tracks_newest_frames():
    scene = make_scene(3, 2)
    rng = np.random.default_rng(0)
    n_t = 40
    truth = np.zeros((n_t, scene.n, 3))
    truth[..., 0] = 0.1 * np.arange(n_t)[:, None] * scene.cfg.m_per_px
    frames = [scene.render(p, rng) for p in truth]
    got = {}
    lock = threading.Lock()

    def publish(stamp, poses):
        time.sleep(0.02)  # a slow consumer must not slow the camera
        with lock:
            got[stamp] = poses

    tracker = DICTracker(scene.polygons_m, scene.calib)
    live = LivePreview(tracker, rate_hz=50.0, publish=publish).start()
    try:
        worst = 0.0
        for k, f in enumerate(frames):
            t0 = time.perf_counter()
            live.offer(k, f)
            worst = max(worst, time.perf_counter() - t0)
            time.sleep(0.002)  # a 500 fps camera
        # blocking would wait for the consumer (>= 20 ms, its sleep above); the margin below
        # that is for a loaded machine (the tracker thread can hold the GIL for a 5 ms slice)
        assert worst < 0.015
        _wait(lambda: live.stats().offered == n_t and n_t - 1 in got)
    finally:
        live.close()
    st = live.stats()
    assert st.offered == n_t and st.tracked == len(got)
    assert 2 <= st.tracked < n_t and st.skipped > 0  # decimated
    k_ref = min(got)  # the first frame tracked is the reference configuration
    for k, poses in got.items():
        assert not poses.lost.any()
        pos, _ = errors_px(scene, poses.q, truth[k] - truth[k_ref])
        assert pos < 0.01
    x, _, _ = to_absolute(got[n_t - 1].q, area_centroids(scene.polygons_m))
    c = area_centroids(scene.polygons_m)
    np.testing.assert_allclose(x - c[:, 0], truth[-1][:, 0] - truth[k_ref][:, 0],
                               atol=0.01 * scene.cfg.m_per_px)


def test_reset_reference_and_bad_frames():
    scene = make_scene(2, 1)
    rng = np.random.default_rng(1)
    shifted = scene.render(np.tile(scene.px([1.0, 0.0, 0.0]), (scene.n, 1)), rng)
    base = scene.render(np.zeros((scene.n, 3)), rng)
    got = []
    live = LivePreview(DICTracker(scene.polygons_m, scene.calib), 200.0,
                       lambda s, p: got.append((s, p))).start()
    try:
        live.offer(0, np.zeros_like(base))  # blank: cannot be the reference, nothing published
        _wait(lambda: live.stats().offered == 1)
        time.sleep(0.05)
        live.offer(1, base)
        _wait(lambda: len(got) == 1)
        live.offer(2, shifted)
        _wait(lambda: len(got) == 2)
        live.offer(3, np.zeros((5, 5), np.uint8))  # wrong size: all lost, not a crash
        _wait(lambda: len(got) == 3)
        live.reset_reference()
        live.offer(4, shifted)  # becomes the new reference
        _wait(lambda: len(got) == 4)
    finally:
        live.close()
    assert [s for s, _ in got] == [1, 2, 3, 4]
    np.testing.assert_allclose(got[1][1].q[:, 0], scene.cfg.m_per_px, rtol=0.01)
    assert got[2][1].lost.all() and got[2][1].error
    np.testing.assert_allclose(got[3][1].q[:, 0], 0.0, atol=1e-9)


def test_node_config_calibration(tmp_path):
    cfg = DICNodeConfig(m_per_px=1e-3, origin_col=5.0, origin_row=50.0, fps=500.0)
    cal = cfg.calibration()
    assert cal.fps == 500.0 and cal.origin_px == (5.0, 50.0)
    assert cfg.tracker.search_radius_px == 24 and cfg.tracker.lost_search_radius_px == 48
    with pytest.raises(ValueError):
        DICNodeConfig(m_per_px=-1.0).calibration()
    with pytest.raises(ValueError, match="rate_hz"):
        LivePreview(None, 0.0, print)
