"""Camera source node for real: the sample recordings and an image folder replay through it."""

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from rostools import call, spin_until, stop_process, wait_matched

from ros_nodes import topics as T

RECORDINGS = sorted((Path(__file__).resolve().parents[2] / "recordings").glob("*/recording.mcap"))


def _replay(viewer, start_node, *params):
    from rosgraph_msgs.msg import Clock
    from sensor_msgs.msg import Image
    from std_msgs.msg import String
    from std_srvs.srv import Trigger

    from ros_nodes.nodes._common import LATCHED, STREAM

    node, ex = viewer
    got, clock, status = [], [], []
    sub = node.create_subscription(Image, T.IMAGE.name, got.append, STREAM)
    clock_sub = node.create_subscription(Clock, "/clock", clock.append, 100)
    node.create_subscription(String, "/camera/status", lambda m: status.append(json.loads(m.data)),
                             LATCHED)
    args = ["-p", "rate_factor:=0.0", "-p", "publish_clock:=true"]
    for p in params:
        args += ["-p", p]
    proc = start_node("metarig-camera", *args)
    try:
        wait_matched(sub, ex)
        wait_matched(clock_sub, ex)
        assert call(node.create_client(Trigger, "/camera/start"), Trigger.Request(), ex).success
        spin_until(ex, lambda: status and status[-1]["state"] in ("done", "error"), 60, "replay")
        assert status[-1]["state"] == "done", status[-1]
        spin_until(ex, lambda: len(got) >= status[-1]["frames"], 20, "all frames")
    finally:
        print(stop_process(proc))
    return got, clock


@pytest.mark.parametrize("path", RECORDINGS, ids=[p.parent.name for p in RECORDINGS])
def test_sample_recordings_replay(ros_node, start_node, path):
    from tracking.frame_sources import mcap_frames

    frames = list(mcap_frames(path, T.IMAGE.name))
    assert len(frames) >= 40
    got, clock = _replay(ros_node, start_node, "source:=mcap", f"path:={path}")
    assert len(got) == len(frames)
    for (t, f), m in zip(frames, got):
        assert m.header.stamp.sec * 10**9 + m.header.stamp.nanosec == t
        assert np.array_equal(np.asarray(m.data).reshape(m.height, m.width), f)
    # /clock follows the replayed stamps (a time source, keep-last 10: ticks may be merged when
    # replaying as fast as possible, but it never goes back and every tick is a frame stamp)
    ct = [c.clock.sec * 10**9 + c.clock.nanosec for c in clock]
    assert np.all(np.diff(ct) > 0) and set(ct) <= {t for t, _ in frames}
    assert len(ct) > len(frames) // 2


def test_image_folder_replays_in_name_order(ros_node, start_node, tmp_path):
    for k in range(12):
        cv2.imwrite(str(tmp_path / f"f{k:03d}.png"), np.full((30, 40), 10 * k, np.uint8))
    got, _ = _replay(ros_node, start_node, "source:=folder", f"path:={tmp_path}", "fps:=500.0")
    assert [int(m.data[0]) for m in got] == [10 * k for k in range(12)]
    assert got[1].header.stamp.nanosec - got[0].header.stamp.nanosec == 2_000_000


def test_bad_source_is_reported_not_crashed(ros_node, start_node, tmp_path):
    from std_msgs.msg import String
    from std_srvs.srv import Trigger

    from ros_nodes.nodes._common import LATCHED

    node, ex = ros_node
    status = []
    node.create_subscription(String, "/camera/status", lambda m: status.append(json.loads(m.data)),
                             LATCHED)
    proc = start_node("metarig-camera", "-p", "source:=folder", "-p", f"path:={tmp_path}")
    try:
        assert call(node.create_client(Trigger, "/camera/start"), Trigger.Request(), ex).success
        spin_until(ex, lambda: status and status[-1]["state"] == "error", 30, "the error status")
        assert "no images" in status[-1]["message"]
        assert proc.poll() is None  # still running
    finally:
        out = stop_process(proc)
    assert "Traceback" not in out
