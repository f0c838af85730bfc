"""Live DIC tracker node for real: frames in on /camera/image_raw, decimated poses out."""

import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from rostools import call, spin_until, stop_process, wait_matched

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from dic_synth import make_scene

from metarig.polygon import area_centroids as polygon_centroids
from ros_nodes import topics as T

NODE = [sys.executable, "-m", "ros_nodes.nodes.dic_tracker_node"]


def _scene_files(tmp_path):
    scene = make_scene(3, 2)
    (tmp_path / "units.json").write_text(json.dumps({"polygons_m": scene.polygons_m.tolist()}))
    (tmp_path / "cal.json").write_text(json.dumps(scene.calib.to_json()))
    return scene


def test_node_tracks_a_burst_at_the_preview_rate(ros_node, start_node, tmp_path):
    from metarig_msgs.msg import UnitPose2DArray
    from sensor_msgs.msg import Image
    from std_srvs.srv import Trigger

    from ros_nodes import convert
    from ros_nodes.nodes._common import STREAM

    node, ex = ros_node
    scene = _scene_files(tmp_path)
    rng = np.random.default_rng(0)
    n_t = 60
    truth = np.zeros((n_t, scene.n, 3))
    truth[..., 0] = 0.05 * np.arange(n_t)[:, None] * scene.cfg.m_per_px
    truth[..., 2] = 0.001 * np.arange(n_t)[:, None]
    frames = [scene.render(p, rng) for p in truth]
    got: list = []
    pub = node.create_publisher(Image, T.IMAGE.name, STREAM)
    sub = node.create_subscription(UnitPose2DArray, "/dic/poses", got.append, STREAM)
    proc = start_node(NODE, "-p", f"units_path:={tmp_path / 'units.json'}",
                      "-p", f"calibration_path:={tmp_path / 'cal.json'}",
                      "-p", "preview_rate_hz:=20.0")
    try:
        wait_matched(pub, ex, timeout_s=60)
        wait_matched(sub, ex, timeout_s=60)
        t0 = time.monotonic()
        for k, f in enumerate(frames):  # a 500 fps burst, far above the preview rate
            pub.publish(convert.image(k * 2_000_000, f))
            ex.spin_once(timeout_sec=0.002)
        burst_s = time.monotonic() - t0
        spin_until(ex, lambda: got and convert.to_ns(got[-1].header.stamp) == (n_t - 1) * 2e6,
                   30, "the pose of the last frame")
        # a second burst after a reset: its first frame becomes the reference
        res = call(node.create_client(Trigger, "/dic_tracker/reset_reference"),
                   Trigger.Request(), ex)
        assert res.success
        n_before = len(got)
        pub.publish(convert.image(10**9, frames[-1]))
        spin_until(ex, lambda: len(got) > n_before, 30, "the pose after a reset")
    finally:
        out = stop_process(proc)
    assert burst_s < 2.0, out
    stamps = [convert.to_ns(m.header.stamp) for m in got[:n_before]]
    assert 2 <= len(stamps) < n_t, out  # decimated, not one message per frame
    c0 = polygon_centroids(scene.polygons_m)
    k_ref = stamps[0] // 2_000_000
    for m, s in zip(got[:n_before], stamps, strict=True):
        k = s // 2_000_000
        assert list(m.ids) == list(range(scene.n)) and not any(m.lost)
        u = np.asarray(m.x) - c0[:, 0]
        expect = truth[k, :, 0] - truth[k_ref, :, 0]
        np.testing.assert_allclose(u, expect, atol=0.02 * scene.cfg.m_per_px)
        assert np.all(np.asarray(m.quality) > 0.99)
    after = got[-1]
    np.testing.assert_allclose(np.asarray(after.x) - c0[:, 0], 0.0, atol=1e-9)


def test_node_waits_for_the_design_topic_and_refuses_bad_files(ros_node, start_node, ros_env,
                                                               tmp_path):
    from metarig_msgs.msg import UnitPose2DArray
    from sensor_msgs.msg import Image
    from std_msgs.msg import String

    from ros_nodes import convert
    from ros_nodes.nodes._common import LATCHED, STREAM

    node, ex = ros_node
    scene = _scene_files(tmp_path)
    (tmp_path / "bad.json").write_text("{}")
    bad = subprocess.run([*NODE, "--ros-args", "-p", f"units_path:={tmp_path / 'bad.json'}"],
                         env=ros_env, capture_output=True, text=True, timeout=60, check=False)
    assert bad.returncode == 2 and "polygons_m" in bad.stdout + bad.stderr
    design = node.create_publisher(String, "/rig/design", LATCHED)
    design.publish(String(data=json.dumps({"scene": "x",
                                           "polygons_m": scene.polygons_m.tolist()})))
    pub = node.create_publisher(Image, T.IMAGE.name, STREAM)
    got: list = []
    sub = node.create_subscription(UnitPose2DArray, "/dic/poses", got.append, STREAM)
    cal = scene.calib
    proc = start_node(NODE, "-p", f"m_per_px:={cal.m_per_px}",
                      "-p", f"origin_col:={cal.origin_px[0]}",
                      "-p", f"origin_row:={cal.origin_px[1]}", "-p", f"fps:={cal.fps}")
    try:
        wait_matched(sub, ex, timeout_s=60)
        wait_matched(pub, ex, timeout_s=60)
        frame = scene.render(np.zeros((scene.n, 3)), np.random.default_rng(0))

        def poke():
            pub.publish(convert.image(0, frame))
            ex.spin_once(timeout_sec=0.1)
            return bool(got)

        spin_until(ex, poke, 30, "poses once the design arrived")
    finally:
        out = stop_process(proc)
    assert len(got[0].ids) == scene.n and not any(got[0].lost), out


def test_node_tracks_from_the_cameras_averaged_snapshot(ros_node, start_node, tmp_path):
    """The camera's snapshot (`snapshot_frames` frames at rest, averaged) on the latched
    /camera/reference_image is the node's reference: a sample already displaced in every frame
    the node sees (pre-compressed) is reported displaced, from the snapshot's configuration;
    without the snapshot the first frame would be the reference and every pose 0."""
    from metarig_msgs.msg import UnitPose2DArray
    from sensor_msgs.msg import Image

    from hardware_sim.camera import REFERENCE_FRAMES, average_frames
    from ros_nodes import convert
    from ros_nodes.nodes._common import LATCHED, STREAM

    node, ex = ros_node
    scene = _scene_files(tmp_path)
    rng = np.random.default_rng(3)
    at_rest = np.zeros((scene.n, 3))
    snapshot = average_frames([scene.render(at_rest, rng) for _ in range(REFERENCE_FRAMES)])
    moved = np.zeros((scene.n, 3))
    moved[:, 0] = 1.3 * scene.cfg.m_per_px
    moved[:, 1] = -0.6 * scene.cfg.m_per_px
    moved[:, 2] = 0.01
    frame = scene.render(moved, rng)
    ref_pub = node.create_publisher(Image, T.REFERENCE_IMAGE.name, LATCHED)
    ref_pub.publish(convert.image(0, snapshot))
    pub = node.create_publisher(Image, T.IMAGE.name, STREAM)
    got: list = []
    sub = node.create_subscription(UnitPose2DArray, "/dic/poses", got.append, STREAM)
    proc = start_node(NODE, "-p", f"units_path:={tmp_path / 'units.json'}",
                      "-p", f"calibration_path:={tmp_path / 'cal.json'}")
    try:
        wait_matched(ref_pub, ex, timeout_s=60)
        wait_matched(pub, ex, timeout_s=60)
        wait_matched(sub, ex, timeout_s=60)
        ex.spin_once(timeout_sec=0.5)  # the latched snapshot reaches the node first

        def poke():
            pub.publish(convert.image(10**6 * (len(got) + 1), frame))
            ex.spin_once(timeout_sec=0.2)
            return bool(got)

        spin_until(ex, poke, 30, "poses from the snapshot")
    finally:
        out = stop_process(proc)
    m = got[0]
    assert not any(m.lost), out
    c0 = polygon_centroids(scene.polygons_m)
    np.testing.assert_allclose(np.asarray(m.x) - c0[:, 0], moved[:, 0],
                               atol=0.03 * scene.cfg.m_per_px)
    np.testing.assert_allclose(np.asarray(m.y) - c0[:, 1], moved[:, 1],
                               atol=0.03 * scene.cfg.m_per_px)
    np.testing.assert_allclose(np.asarray(m.theta), moved[:, 2], atol=1e-3)
