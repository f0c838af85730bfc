"""The MCAP recorder logic (`ros_nodes.logic.recorder`) without rclpy: write a file through it,
read it back with independent readers (`mcap`, `rosbags`), check counts and loss accounting."""

import json

import numpy as np
import pytest
from mcap.reader import make_reader

from ros_nodes import topics
from ros_nodes.logic.cdr import ImageEncoder, header_stamp_ns
from ros_nodes.logic.recorder import McapRecorder, QueuedRecorder

T0 = 1_000_000_000  # first frame stamp, ns
PERIOD = 1_000_000  # 1000 fps, ns


def _string_cdr(text: str) -> bytes:
    """std_msgs/String in little-endian CDR: header, uint32 length (with NUL), bytes, NUL."""
    b = text.encode() + b"\x00"
    return b"\x00\x01\x00\x00" + len(b).to_bytes(4, "little") + b


def _record(path, ks, seqs, **kw):
    enc = ImageEncoder(6, 8, np.uint8, "camera")
    rec = McapRecorder(path, chunk_size=4096, **kw)
    rec.add_topic(topics.IMAGE.name, topics.IMAGE.type)
    rec.add_topic(topics.RIG_DESIGN.name, topics.RIG_DESIGN.type)
    rec.write(topics.RIG_DESIGN.name, _string_cdr(json.dumps({"polygons_m": []})), T0 - 5, 1)
    for k, seq in zip(ks, seqs, strict=True):
        # the frame arrives 3 ms after its stamp; the pixels carry k
        rec.write(topics.IMAGE.name, enc.encode(T0 + k * PERIOD, np.full((6, 8), k, np.uint8)),
                  T0 + k * PERIOD + 3_000_000, seq)
    return rec.close()


def test_a_recording_reads_back_with_mcap_and_rosbags(tmp_path):
    from rosbags.highlevel import AnyReader

    path = tmp_path / "r.mcap"
    report = _record(path, range(20), range(1, 21))
    assert report["messages"] == 21 and report["dropped"] == 0
    cam = report["topics"][topics.IMAGE.name]
    assert cam["count"] == 20 and cam["gaps"] == 0 and cam["missing_by_sequence"] == 0
    assert cam["period_s"] == pytest.approx(1e-3)
    assert cam["max_latency_ms"] == pytest.approx(3.0)
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert reader.get_header().profile == "ros2"
        assert {c.topic: c.message_encoding for c in summary.channels.values()} == {
            topics.IMAGE.name: "cdr", topics.RIG_DESIGN.name: "cdr"}
        assert {s.name for s in summary.schemas.values()} == {"sensor_msgs/msg/Image",
                                                             "std_msgs/msg/String"}
        msgs = [(c.topic, m.log_time, m.publish_time, m.data)
                for _, c, m in reader.iter_messages(log_time_order=False)]
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
    frames = [m for m in msgs if m[0] == topics.IMAGE.name]
    # stamped messages are logged at their header stamp, published at the receive time
    assert [t for _, t, _, _ in frames] == [T0 + k * PERIOD for k in range(20)]
    assert all(p - t == 3_000_000 for _, t, p, _ in frames)
    assert [header_stamp_ns(d) for *_, d in frames] == [T0 + k * PERIOD for k in range(20)]
    assert json.loads(meta["recording_report"]["json"])["messages"] == 21
    with AnyReader([path]) as reader:
        got = [(c.topic, reader.deserialize(raw, c.msgtype)) for c, _, raw in reader.messages()]
    images = [m for t, m in got if t == topics.IMAGE.name]
    assert [int(m.data[0]) for m in images] == list(range(20))
    assert (images[0].height, images[0].width, images[0].encoding) == (6, 8, "mono8")
    assert json.loads(next(m for t, m in got if t == topics.RIG_DESIGN.name).data) == {
        "polygons_m": []}


def test_losses_are_counted_by_sequence_and_by_stamp(tmp_path):
    # frames 10-12 never reached the recorder (transport loss: sequence 11-13 missing);
    # frame 30 was never published (the camera skipped it: same sequence, a stamp gap)
    ks = [k for k in range(40) if k not in (10, 11, 12, 30)]
    seqs = [k + 1 if k < 30 else k for k in ks]
    report = _record(tmp_path / "lossy.mcap", ks, seqs)
    cam = report["topics"][topics.IMAGE.name]
    assert cam["count"] == len(ks) == 36
    assert cam["missing_by_sequence"] == 3 and cam["dropped"] == 3 and report["dropped"] == 3
    assert cam["gaps"] == 2 and cam["missing_by_stamp"] == 4
    assert cam["backwards"] == 0


def test_stamps_that_go_backwards_are_counted(tmp_path):
    report = _record(tmp_path / "back.mcap", [0, 1, 2, 3, 4, 5, 3, 6], range(1, 9))
    assert report["topics"][topics.IMAGE.name]["backwards"] == 1


def test_the_queued_writer_keeps_order_and_counts_overflow_once(tmp_path):
    path = tmp_path / "q.mcap"
    rec = QueuedRecorder(McapRecorder(path), max_queue=100_000)
    rec.call("add_topic", "/t", "std_msgs/msg/String")
    for k in range(300):
        assert rec.put("/t", _string_cdr(str(k)), 1_000 + k, k + 1)
    report = rec.close()
    assert report["topics"]["/t"]["count"] == 300 and report["dropped"] == 0
    assert not rec.put("/t", _string_cdr("late"), 9_999, 301)  # closed: refused, not written
    with open(path, "rb") as f:
        data = [m.data for _, _, m in make_reader(f).iter_messages(log_time_order=False)]
    assert [d[8:-1].decode() for d in data] == [str(k) for k in range(300)]


def test_unknown_compression_is_refused(tmp_path):
    with pytest.raises(ValueError, match="compression"):
        McapRecorder(tmp_path / "x.mcap", compression="gzip")
