"""Frames for offline tracking: a folder of PNG images, a video file or an MCAP recording.

Every source yields `(k, frame)` in order, k = 0, 1, ... the frame index (time k / fps); a
frame that cannot be decoded is yielded as a `BadFrame` carrying the reason, so the tracker
flags that frame lost and carries on. Sources that cannot be opened at all raise
`SourceError`. MCAP images (`sensor_msgs/msg/Image`) are decoded with `mcap_ros2` (no ROS
install needed). The camera node has its own replay iterators (`replay.py`), which stop at the
first bad frame; these keep going and can count frames ahead for a progress bar.
"""

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

VIDEO_SUFFIXES = (".avi", ".mp4", ".mkv", ".mov", ".m4v", ".mpg", ".mpeg", ".wmv")
IMAGE_MSG = "sensor_msgs/msg/Image"
_ENCODINGS = {
    "mono8": (np.uint8, 1), "8UC1": (np.uint8, 1), "mono16": (np.uint16, 1),
    "16UC1": (np.uint16, 1), "rgb8": (np.uint8, 3), "bgr8": (np.uint8, 3),
    "rgba8": (np.uint8, 4), "bgra8": (np.uint8, 4),
}


class SourceError(ValueError):
    """A frame source that cannot be opened (the message names it and says why)."""


@dataclass(frozen=True, slots=True)
class BadFrame:
    """Placeholder for a frame that could not be decoded."""

    reason: str


@dataclass(frozen=True, slots=True)
class SourceSpec:
    """Where frames come from.

    Attributes:
        path: folder, video file or `.mcap` file.
        kind: "folder", "video" or "mcap".
        topic: MCAP image topic (resolved when the source is opened).
    """

    path: str
    kind: str
    topic: str | None = None


def _mcap_reader(f):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    return make_reader(f, decoder_factories=[DecoderFactory()])


def _image_topics(path: Path) -> dict[str, int]:
    """{topic: message count} of the `sensor_msgs/msg/Image` channels of an MCAP file."""
    try:
        with open(path, "rb") as f:
            summary = _mcap_reader(f).get_summary()
    except Exception as exc:  # noqa: BLE001 - the mcap reader raises assorted types
        raise SourceError(f"{path}: not a readable MCAP file ({exc})") from None
    if summary is None:
        raise SourceError(f"{path}: MCAP file has no summary (unfinished recording? run "
                          "`metarig recover` on it first)")
    counts = summary.statistics.channel_message_counts if summary.statistics else {}
    out = {}
    for cid, ch in summary.channels.items():
        schema = summary.schemas.get(ch.schema_id)
        if schema is not None and schema.name == IMAGE_MSG:
            out[ch.topic] = int(counts.get(cid, 0))
    return out


def open_source(path: str | Path, topic: str | None = None) -> SourceSpec:
    """Identify a source and check that it can be read.

    Args:
        path: a folder of `*.png` images, a video file or an `.mcap` recording.
        topic: MCAP image topic; by default the only image topic, or the one ending in
            `image_raw`.

    Raises:
        SourceError: missing path, no frames, unknown type or ambiguous topic.
    """
    p = Path(path)
    if not p.exists():
        raise SourceError(f"{p}: no such file or folder")
    if p.is_dir():
        if not any(p.glob("*.png")):
            raise SourceError(f"{p}: folder holds no *.png images")
        return SourceSpec(str(p), "folder")
    if p.suffix.lower() == ".mcap":
        topics = _image_topics(p)
        if topic is None:
            raw = [t for t in topics if t.endswith("image_raw")]
            if len(topics) == 1:
                topic = next(iter(topics))
            elif len(raw) == 1:
                topic = raw[0]
            else:
                raise SourceError(f"{p}: choose an image topic with --topic (found: "
                                  f"{', '.join(sorted(topics)) or 'none'})")
        elif topic not in topics:
            raise SourceError(f"{p}: no {IMAGE_MSG} topic {topic!r} (found: "
                              f"{', '.join(sorted(topics)) or 'none'})")
        return SourceSpec(str(p), "mcap", topic)
    if p.suffix.lower() in VIDEO_SUFFIXES:
        cap = cv2.VideoCapture(str(p))
        ok = cap.isOpened()
        cap.release()
        if not ok:
            raise SourceError(f"{p}: cannot open video")
        return SourceSpec(str(p), "video")
    raise SourceError(f"{p}: not a folder, a video ({', '.join(VIDEO_SUFFIXES)}) or .mcap")


def count_frames(spec: SourceSpec) -> int | None:
    """Number of frames the source holds (video: as the container says; None if unknown)."""
    if spec.kind == "folder":
        return len(list(Path(spec.path).glob("*.png")))
    if spec.kind == "mcap":
        return _image_topics(Path(spec.path)).get(spec.topic or "", 0)
    cap = cv2.VideoCapture(spec.path)
    n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
    cap.release()
    return n if n > 0 else None


def image_from_msg(msg) -> np.ndarray:
    """A decoded `sensor_msgs/Image` (any object with its fields) -> [h, w] or [h, w, c] array.

    Raises:
        ValueError: unsupported encoding or a data size that does not match the header.
    """
    enc = _ENCODINGS.get(msg.encoding)
    if enc is None:
        raise ValueError(f"unsupported image encoding {msg.encoding!r}")
    dtype, ch = enc
    dt = np.dtype(dtype).newbyteorder(">" if msg.is_bigendian else "<")
    data = np.frombuffer(bytes(msg.data), dtype=dt)
    row_items = msg.step // dt.itemsize
    if msg.height == 0 or row_items < msg.width * ch or data.size < msg.height * row_items:
        raise ValueError(f"image data ({data.size} values) does not fit {msg.height}x"
                         f"{msg.width}x{ch} with step {msg.step}")
    img = data[: msg.height * row_items].reshape(msg.height, row_items)[:, : msg.width * ch]
    img = img.reshape(msg.height, msg.width, ch) if ch > 1 else img
    if msg.encoding.startswith("rgb"):
        img = img[..., [2, 1, 0] + ([3] if ch == 4 else [])]
    return np.ascontiguousarray(img.astype(dtype, copy=False))


def _folder(spec: SourceSpec) -> Iterator[tuple[int, np.ndarray | BadFrame]]:
    files = sorted(Path(spec.path).glob("*.png"))
    for k, f in enumerate(files):
        img = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
        yield k, (img if img is not None else BadFrame(f"{f.name}: cannot decode image"))


def _video(spec: SourceSpec) -> Iterator[tuple[int, np.ndarray | BadFrame]]:
    cap = cv2.VideoCapture(spec.path)
    try:
        k = 0
        while True:
            ok, img = cap.read()
            if not ok:
                break
            yield k, img
            k += 1
    finally:
        cap.release()


def _mcap(spec: SourceSpec) -> Iterator[tuple[int, np.ndarray | BadFrame]]:
    with open(spec.path, "rb") as f:
        reader = _mcap_reader(f)
        messages = reader.iter_decoded_messages(topics=[spec.topic], log_time_order=True)
        for k, (_schema, _channel, message, decoded) in enumerate(messages):
            try:
                yield k, image_from_msg(decoded)
            except ValueError as exc:
                yield k, BadFrame(f"message at log time {message.log_time} ns: {exc}")


def iter_frames(spec: SourceSpec) -> Iterator[tuple[int, np.ndarray | BadFrame]]:
    """Frames of the source in order: (k, image or BadFrame), k = 0, 1, ..."""
    return {"folder": _folder, "video": _video, "mcap": _mcap}[spec.kind](spec)
