"""Recordings open in Rerun with the camera frames as images (`ros_nodes.logic.rerun_frames`).

Rerun's MCAP importer turns every single-channel `sensor_msgs/Image` (mono8 included) into a
`DepthImage`; a PNG `sensor_msgs/CompressedImage` beside it becomes an `EncodedImage`. Written
through the real recorder, read back with Rerun's own MCAP reader (what the viewer runs) and with
`rosbags` (the independent reader the replay and tests rely on).
"""

import numpy as np
import pytest

from ros_nodes import topics
from ros_nodes.logic import rerun_frames as rf
from ros_nodes.logic.cdr import ImageEncoder, parse_image
from ros_nodes.logic.recorder import McapRecorder

rc = pytest.importorskip("rerun.chunk")

T0 = 1_000_000_000
PERIOD = 1_000_000  # 1000 fps
PREVIEW = rf.preview_topic(topics.IMAGE.name)


def _speckle(k: int, shape=(24, 32), dtype=np.uint8) -> np.ndarray:
    hi = 256 if dtype == np.uint8 else 65536
    return np.random.default_rng(k).integers(0, hi, shape).astype(dtype)


def _record(path, n=12, *, min_period_ns=0, dtype=np.uint8, shape=(24, 32)):
    """Raw frames + their previews through McapRecorder, as the recorder will write them."""
    enc = ImageEncoder(*shape, dtype, "camera")
    preview = rf.FramePreview(min_period_ns)
    raws = []
    with McapRecorder(path, chunk_size=64 << 10) as rec:
        rec.add_topic(topics.IMAGE.name, topics.IMAGE.type)
        rec.add_topic(PREVIEW, rf.PREVIEW_TYPE)
        for k in range(n):
            cdr = enc.encode(T0 + k * PERIOD, _speckle(k, shape, dtype))
            receive = T0 + k * PERIOD + 2_000_000
            rec.write(topics.IMAGE.name, cdr, receive, k + 1)
            raws.append(cdr)
            png = preview.offer(cdr)
            if png is not None:
                rec.write(PREVIEW, png, receive)
        report = rec.report()
    return raws, report


def _rerun_entities(path) -> dict[str, list]:
    """{entity path: [record batches with data columns]} as Rerun's MCAP importer makes them."""
    out: dict[str, list] = {}
    for chunk in rc.McapReader(path).stream():
        batch = chunk.to_record_batch()
        if any(":" in n and not n.startswith("Mcap") for n in batch.schema.names):
            out.setdefault(str(chunk.entity_path), []).append(batch)
    return out


def _components(batches) -> set[str]:
    return {n for b in batches for n in b.schema.names if ":" in n}


def _blobs_by_stamp(batches) -> list[tuple[int, bytes]]:
    rows = []
    for b in batches:
        stamps = b.column("ros2_timestamp").cast("int64").to_pylist()
        for t, cell in zip(stamps, b.column("EncodedImage:blob").to_pylist(), strict=True):
            assert len(cell) == 1
            rows.append((t, bytes(cell[0])))
    return sorted(rows)


def test_png_is_lossless_and_standard():
    import cv2

    for dtype in (np.uint8, np.uint16):
        f = _speckle(3, (17, 23), dtype)
        png = rf.encode_png(f)
        assert np.array_equal(rf.decode_png(png), f)
        back = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)
        assert back.dtype == dtype and np.array_equal(back, f)
        assert np.array_equal(rf.decode_png(rf.encode_png(f, level=0)), f)
    with pytest.raises(ValueError):
        rf.encode_png(np.zeros((2, 2, 3), np.uint8))


def test_frames_open_in_rerun_as_encoded_images(tmp_path):
    path = tmp_path / "rec.mcap"
    _, report = _record(path)
    assert report["topics"][PREVIEW]["count"] == 12
    entities = _rerun_entities(path)
    # the preview is an EncodedImage whose PNG holds exactly the raw frame
    preview = entities[PREVIEW]
    assert "EncodedImage:blob" in _components(preview)
    assert not {"DepthImage:buffer", "EncodedDepthImage:blob"} & _components(preview)
    blobs = _blobs_by_stamp(preview)
    assert [t for t, _ in blobs] == [T0 + k * PERIOD for k in range(12)]
    for k, (_, png) in enumerate(blobs):
        assert png.startswith(b"\x89PNG\r\n\x1a\n")
        assert np.array_equal(rf.decode_png(png), _speckle(k))
    # the raw stream is still there, as Rerun 0.41 shows mono8: a depth image (the reason for
    # the preview; if this starts failing, Rerun may have learned to show mono8 as an Image)
    assert {"DepthImage:buffer", "DepthImage:format"} <= _components(entities[topics.IMAGE.name])


def test_rosbags_still_reads_raw_frames_and_previews(tmp_path):
    from mcap.reader import make_reader
    from rosbags.highlevel import AnyReader

    path = tmp_path / "rec.mcap"
    raws, _ = _record(path, n=6)
    with open(path, "rb") as f:  # the raw stream is byte for byte what the camera sent
        stored = [m.data for _, _, m in make_reader(f).iter_messages(topics=[topics.IMAGE.name])]
    assert stored == raws
    with AnyReader([path]) as reader:
        assert {c.topic: c.msgtype for c in reader.connections} == {
            topics.IMAGE.name: "sensor_msgs/msg/Image", PREVIEW: "sensor_msgs/msg/CompressedImage"}
        got = {topics.IMAGE.name: [], PREVIEW: []}
        for con, t_ns, raw in reader.messages():
            msg = reader.deserialize(raw, con.msgtype)
            assert t_ns == msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
            assert msg.header.frame_id == "camera"
            got[con.topic].append(msg)
    assert len(got[topics.IMAGE.name]) == len(got[PREVIEW]) == 6
    for k, (img, comp) in enumerate(zip(got[topics.IMAGE.name], got[PREVIEW], strict=True)):
        assert img.encoding == "mono8"
        assert comp.format == "mono8; png compressed "
        assert np.array_equal(rf.decode_png(bytes(comp.data)), _speckle(k))
        assert img.header.stamp == comp.header.stamp


def test_mono16_previews_are_16_bit_pngs(tmp_path):
    path = tmp_path / "rec16.mcap"
    _record(path, n=3, dtype=np.uint16)
    blobs = _blobs_by_stamp(_rerun_entities(path)[PREVIEW])
    assert len(blobs) == 3
    for k, (_, png) in enumerate(blobs):
        f = rf.decode_png(png)
        assert f.dtype == np.uint16 and np.array_equal(f, _speckle(k, dtype=np.uint16))


def test_previews_are_decimated_by_stamp():
    p = rf.FramePreview(4 * PERIOD)
    enc = ImageEncoder(4, 4, np.uint8)
    frame = np.zeros((4, 4), np.uint8)
    stamps = [T0 + k * PERIOD for k in range(10)] + [T0 + 2 * PERIOD]  # last: a new take
    made = [s for s in stamps if p.offer(enc.encode(s, frame)) is not None]
    assert made == [T0, T0 + 4 * PERIOD, T0 + 8 * PERIOD, T0 + 2 * PERIOD]
    assert (p.offered, p.made) == (11, 4)
    # colour frames need no preview: Rerun shows them as images already
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_JAZZY)
    Image, Header, Time = (ts.types[n] for n in ("sensor_msgs/msg/Image", "std_msgs/msg/Header",
                                                 "builtin_interfaces/msg/Time"))
    rgb = ts.serialize_cdr(Image(Header(Time(1, 0), "camera"), 2, 2, "rgb8", 0, 6,
                                 np.zeros(12, np.uint8)), "sensor_msgs/msg/Image")
    assert parse_image(rgb).encoding == "rgb8"
    assert rf.FramePreview().offer(rgb) is None


def test_compressed_frame_from_an_array_or_a_raw_message():
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_JAZZY)
    f = _speckle(5)
    a = rf.compressed_frame(f, T0 + 7, frame_id="cam")
    b = rf.compressed_frame(ImageEncoder(*f.shape, np.uint8, "cam").encode(T0 + 7, f))
    assert a == b
    msg = ts.deserialize_cdr(a, "sensor_msgs/msg/CompressedImage")
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec, msg.header.frame_id) == (1, 7, "cam")
    assert np.array_equal(rf.decode_png(bytes(msg.data)), f)
    with pytest.raises(ValueError):
        rf.compressed_frame(f)  # an array needs a stamp


def test_finished_recordings_get_previews_and_convert_to_rrd(tmp_path):
    enc = ImageEncoder(24, 32, np.uint8, "camera")
    src = tmp_path / "old.mcap"
    with McapRecorder(src) as rec:  # a recording from before the recorder wrote previews
        rec.add_topic(topics.IMAGE.name, topics.IMAGE.type)
        for k in range(8):
            rec.write(topics.IMAGE.name, enc.encode(T0 + k * PERIOD, _speckle(k)), T0 + k * PERIOD)
    dst = tmp_path / "new.mcap"
    assert rf.add_previews(src, dst, min_period_ns=2 * PERIOD) == 4
    assert rf.add_previews(dst, dst) == 8  # re-running replaces the previews, in place
    blobs = _blobs_by_stamp(_rerun_entities(dst)[PREVIEW])
    assert [t for t, _ in blobs] == [T0 + k * PERIOD for k in range(8)]
    # the .rrd route: raw frames become Images, no preview needed
    rrd = rf.to_rrd(src, tmp_path / "old.rrd")
    comps: set[str] = set()
    frames = []
    for chunk in rc.RrdReader(rrd).stream():
        if str(chunk.entity_path) == topics.IMAGE.name:
            b = chunk.to_record_batch()
            comps |= set(b.schema.names)
            if "Image:buffer" in b.schema.names:
                frames += [np.asarray(c[0], np.uint8) for c in b.column("Image:buffer").to_pylist()]
    assert {"Image:buffer", "Image:format"} <= comps and "DepthImage:buffer" not in comps
    assert len(frames) == 8 and any(np.array_equal(x, _speckle(0).ravel()) for x in frames)
