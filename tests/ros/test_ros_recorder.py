"""Recorder node for real: loss report, rosbags read-back, metadata, kill -9 then recovery."""

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from rostools import call, spin_until, stop_process, wait_matched

from ros_nodes import topics as T

BIN = sys.prefix + "/bin/"


def _recorder(start_node, path, *extra):
    return start_node("metarig-recorder", "-p", f"path:={path}",
                      "-p", "topics:=[/camera/image_raw,/rig/design]", *extra)


def _frames(pub, ex, ks, shape=(48, 64)):
    from ros_nodes import convert

    for k in ks:
        pub.publish(convert.image(1_000_000_000 + k * 1_000_000, np.full(shape, k % 256, np.uint8)))
        ex.spin_once(timeout_sec=0)


def test_recording_reads_back_in_rosbags_and_reports_a_gap(ros_node, start_node, tmp_path):
    from rosbags.highlevel import AnyReader
    from sensor_msgs.msg import Image
    from std_msgs.msg import String
    from std_srvs.srv import Trigger

    from ros_nodes.nodes._common import LATCHED, STREAM

    node, ex = ros_node
    path = tmp_path / "rec.mcap"
    design = node.create_publisher(String, "/rig/design", LATCHED)
    design.publish(String(data=json.dumps({"polygons_m": [[[0, 0], [1, 0], [0, 1]]]})))
    pub = node.create_publisher(Image, T.IMAGE.name, STREAM)
    proc = _recorder(start_node, path, "-p", "autostart:=true")
    try:
        wait_matched(pub, ex, 20.0)
        wait_matched(design, ex, 20.0)
        sent = [k for k in range(120) if k != 60]  # frame 60 never published: a gap
        _frames(pub, ex, sent)
        stop = node.create_client(Trigger, "/recorder/stop")
        # wait until the recorder says it has written every frame, then ask for the report
        status = []
        node.create_subscription(String, "/recorder/status", lambda m: status.append(
            json.loads(m.data)["counts"].get(T.IMAGE.name, 0)), 10)
        spin_until(ex, lambda: status and status[-1] >= len(sent), 20.0, "all frames written")
        res = call(stop, Trigger.Request(), ex)
        assert res.success
        report = json.loads(res.message)
        t = report["topics"][T.IMAGE.name]
        assert t["count"] == len(sent)
        assert t["gaps"] == 1 and t["missing_by_stamp"] == 1 and t["missing_by_sequence"] == 0
        assert t["period_s"] == pytest.approx(1e-3)
    finally:
        print(stop_process(proc))
    with AnyReader([path]) as reader:
        assert {c.topic for c in reader.connections} == {T.IMAGE.name, "/rig/design"}
        stamps, values = [], []
        for con, t_ns, raw in reader.messages():
            msg = reader.deserialize(raw, con.msgtype)
            if con.topic == T.IMAGE.name:
                stamps.append(t_ns)
                values.append(int(msg.data[0]))
                assert t_ns == msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
            else:
                assert json.loads(msg.data)["polygons_m"]
    assert values == [k % 256 for k in sent]
    assert np.all(np.diff(stamps) > 0)
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        meta = {m.name: m.metadata for m in make_reader(f).iter_metadata()}
    assert "polygons_m" in meta["design"]["json"] and "recording_report" in meta


def test_kill_minus_9_then_recover(ros_node, start_node, ros_env, tmp_path):
    from rosbags.rosbag2 import Reader
    from sensor_msgs.msg import Image

    from ros_nodes.nodes._common import STREAM

    node, ex = ros_node
    path = tmp_path / "killed.mcap"
    pub = node.create_publisher(Image, T.IMAGE.name, STREAM)
    proc = _recorder(start_node, path, "-p", "autostart:=true", "-p", "chunk_size:=32768")
    try:
        wait_matched(pub, ex, 20.0)
        n = 400
        _frames(pub, ex, range(n))
        from rclpy.duration import Duration

        assert pub.wait_for_all_acked(Duration(seconds=20))
        per_frame = 48 * 64 + 60
        # wait (by deadline) until all but the last ~chunk are on disk, then kill hard
        spin_until(ex, lambda: path.exists() and path.stat().st_size > (n - 15) * per_frame,
                   20.0, "the recorder to flush its chunks")
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(10)
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.communicate()
    assert path.stat().st_size > 0
    # the killed file has no summary/footer: any reader error will do, the file exists
    with pytest.raises(Exception):  # noqa: B017
        with Reader(path) as r:
            list(r.messages())
    out = tmp_path / "recovered.mcap"
    r = subprocess.run([BIN + "metarig", "recover", str(path), "-o", str(out)], env=ros_env,
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    rep = json.loads(r.stdout.strip().splitlines()[-1])
    assert not rep["complete"]
    with Reader(out) as reader:
        values = [raw[-1] for _, _, raw in reader.messages()]  # last byte: a pixel of frame k
    assert len(values) == rep["messages"] >= n - 15
    assert values == [k % 256 for k in range(len(values))]  # contiguous from the start


def test_recover_refuses_non_mcap(tmp_path, ros_env):
    bad = tmp_path / "x.mcap"
    bad.write_bytes(b"not an mcap")
    r = subprocess.run([BIN + "metarig", "recover", str(bad)], env=ros_env, capture_output=True,
                       text=True, timeout=60)
    assert r.returncode == 2 and "not an MCAP" in r.stderr and "Traceback" not in r.stderr


def test_hand_built_image_cdr_matches_rclpy():
    """The camera's serialized frames and restamped camera info decode to the same messages."""
    from rclpy.serialization import deserialize_message, serialize_message
    from sensor_msgs.msg import CameraInfo, Image

    from ros_nodes import convert
    from ros_nodes.logic.cdr import ImageEncoder, restamp

    rng = np.random.default_rng(1)
    for shape, dt, fid in [((48, 64), np.uint8, "camera"), ((5, 7), np.uint16, "ab"),
                           ((3, 3), np.uint8, "")]:
        f = rng.integers(0, 255, shape).astype(dt)
        cdr = ImageEncoder(*shape, dt, fid).encode(1_234_567_891_011, f)
        ref = serialize_message(convert.image(1_234_567_891_011, f, fid))
        assert len(cdr) == len(ref)
        assert deserialize_message(cdr, Image) == deserialize_message(ref, Image)
        assert np.array_equal(convert.image_array(deserialize_message(cdr, Image)), f)
    info = serialize_message(convert.camera_info(5, 640, 480, 6e-4))
    assert deserialize_message(restamp(info, 77_000_000_123), CameraInfo) == \
        convert.camera_info(77_000_000_123, 640, 480, 6e-4)


def test_queued_recorder_counts_overflow(tmp_path):
    """A full write queue drops the message and counts it in `dropped` (never silent)."""
    from ros_nodes.logic.recorder import McapRecorder, QueuedRecorder

    rec = QueuedRecorder(McapRecorder(tmp_path / "q.mcap"), max_queue=1)
    rec.call("add_topic", "/t", "std_msgs/msg/String")
    data = b"\x00\x01\x00\x00\x02\x00\x00\x00a\x00"
    results = [rec.put("/t", data, 1_000 + k, k + 1) for k in range(500)]
    report = rec.close()
    t = report["topics"]["/t"]
    assert t["count"] + t["queue_overflow"] == 500
    assert t["count"] == sum(results) and report["dropped"] == t["queue_overflow"]
    assert t["missing_by_sequence"] == 0  # the overflow is not counted twice


def _in_process_recorder(ros_context, path, topics, *extra):
    from rclpy.parameter import Parameter

    from ros_nodes.nodes.recorder_node import RecorderNode

    return RecorderNode(context=ros_context, parameter_overrides=[
        Parameter("path", value=str(path)), Parameter("topics", value=topics),
        Parameter("discovery_period_s", value=0.05), *extra])


def test_bursts_longer_than_the_wait_cycles_are_recorded_whole(ros_context, ros_node, tmp_path):
    """A device node catching up publishes its due samples in one timer call; the executor
    hands a subscription one message per wait cycle, so the recorder sharing it with the
    publisher (the in-process rig) takes the rest of its queue itself or loses the oldest
    (its keep-last queue here: 100; 25 bursts of 40 samples, one per 1 ms tick)."""
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import JointState

    from ros_nodes import convert
    from ros_nodes.nodes._common import qos_profile

    node, ex = ros_node
    topic, bursts, size = "/test/joint_states", 25, 40
    rec = _in_process_recorder(ros_context, tmp_path / "burst.mcap", [topic],
                               Parameter("queue_depth", value=100))
    ex.add_node(rec)
    pub = node.create_publisher(JointState, topic, qos_profile(T.JOINTS_QOS))
    spin_until(ex, lambda: topic in rec._subs and rec.matched(), 20.0, "the recorder subscribed")
    rec.start()
    sent = []

    def burst():
        if len(sent) < bursts * size:
            for _ in range(size):
                k = len(sent)
                pub.publish(convert.shaker_state(1_000_000_000 + k * 1_000_000, k * 1e-6, 0.0))
                sent.append(k)

    node.create_timer(0.001, burst)
    spin_until(ex, lambda: len(sent) == bursts * size, 20.0, "every burst sent")
    deadline = time.monotonic() + 5.0  # what is queued still comes; what was lost does not
    while rec.message_counts().get(topic, 0) < len(sent) and time.monotonic() < deadline:
        ex.spin_once(timeout_sec=0.05)
    report = rec.stop()
    ex.remove_node(rec)
    rec.destroy_node()
    t = report["topics"][topic]
    assert t["count"] == bursts * size and t["dropped"] == 0 and t["missing_by_stamp"] == 0
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    with open(tmp_path / "burst.mcap", "rb") as f:
        got = [round(m.position[0] * 1e6) for _, _, _, m in make_reader(
            f, decoder_factories=[DecoderFactory()]).iter_decoded_messages(topics=[topic])]
    assert got == sent


def test_a_topic_with_two_publishers_is_not_counted_lost_by_sequence(ros_context, ros_node,
                                                                     tmp_path):
    """`/diagnostics` has several publishers (shaker, stage), each numbering its own messages,
    and a message does not say which one sent it: counters that had diverged before the
    recording started (5 against 1) looked like 3 lost messages at the first interleaving."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray

    from ros_nodes.nodes._common import COMMAND

    node, ex = ros_node
    other = rclpy.create_node("other_diagnostics", context=ros_context)
    ex.add_node(other)
    a = node.create_publisher(DiagnosticArray, T.DIAGNOSTICS.name, COMMAND)
    b = other.create_publisher(DiagnosticArray, T.DIAGNOSTICS.name, COMMAND)
    rec = _in_process_recorder(ros_context, tmp_path / "diag.mcap", [T.DIAGNOSTICS.name])
    ex.add_node(rec)
    spin_until(ex, lambda: T.DIAGNOSTICS.name in rec._subs and rec.matched()
               and rec._subs[T.DIAGNOSTICS.name][2].get_publisher_count() == 2, 20.0,
               "the recorder matched both publishers")
    received = []
    node.create_subscription(DiagnosticArray, T.DIAGNOSTICS.name, received.append, COMMAND)
    wait_matched(a, ex, 20.0, count=2)
    wait_matched(b, ex, 20.0, count=2)

    def send(pub, n):
        for _ in range(n):
            pub.publish(DiagnosticArray())
            count = len(received) + 1
            spin_until(ex, lambda c=count: len(received) >= c, 30.0, "the message delivered")

    send(a, 5)
    send(b, 1)  # before the recording: a's count is at 5, b's at 1
    rec.start()
    for pub in (b, a, b, a):  # b 2, a 6, b 3, a 7
        send(pub, 1)
    spin_until(ex, lambda: rec.message_counts().get(T.DIAGNOSTICS.name, 0) >= 4, 30.0,
               "the four messages written")
    report = rec.stop()
    for n in (rec, other):
        ex.remove_node(n)
        n.destroy_node()
    t = report["topics"][T.DIAGNOSTICS.name]
    assert t["count"] == 4 and t["dropped"] == 0 and report["dropped"] == 0
    assert t["missing_by_sequence"] == 0 and t["sequence_checked"] is False
