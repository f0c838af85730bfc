"""Frames from a folder of images, a video file, an MCAP recording or a high-speed camera's
own file (Photron MRAW, Phantom CINE, TIFF stack: `tracking.camera_files`), and a synthetic
pattern.

The one frame reader of the project: `metarig track`, the live DIC node and the camera node's
replay all read frames here. A source is opened once (`open_source` checks it and resolves the
MCAP image topic) and then iterated:

- `iter_frames(spec)` yields `(k, frame)`, k = 0, 1, ... (the tracker: time k / fps). A frame
  that cannot be decoded is yielded as a `BadFrame` carrying the reason, so the tracker flags
  that frame lost and carries on.
- `replay_frames(spec, fps)` yields `(t_ns, frame)` with t_ns the capture time relative to the
  first frame (MCAP: the image header stamps; otherwise k / fps), frames as grey [h, w]
  uint8/uint16, and stops with `SourceError` at the first bad frame (the camera node).

MCAP images (`sensor_msgs/msg/Image`) are read with `mcap_ros2` (no ROS install needed) and
decoded by `image_from_msg`, which also serves ROS messages (`ros_nodes.convert.image_array`).
Every failure to open or read a source is a `SourceError`.
"""

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

PNG = (".png",)
IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".bmp", ".jpg", ".jpeg", ".pgm")
VIDEO_SUFFIXES = (".avi", ".mp4", ".mkv", ".mov", ".m4v", ".mpg", ".mpeg", ".wmv")
KINDS = ("folder", "video", "mcap", "mraw", "cine", "tiff")
CAMERA_FILE_KINDS = ("mraw", "cine", "tiff")  # read by `tracking.camera_files`
IMAGE_MSG = "sensor_msgs/msg/Image"
_ENCODINGS = {
    "mono8": (np.uint8, 1), "8UC1": (np.uint8, 1), "mono16": (np.uint16, 1),
    "16UC1": (np.uint16, 1), "rgb8": (np.uint8, 3), "bgr8": (np.uint8, 3),
    "rgba8": (np.uint8, 4), "bgra8": (np.uint8, 4),
}


class SourceError(ValueError):
    """A frame source that cannot be opened or read (the message names it and says why)."""


@dataclass(frozen=True, slots=True)
class BadFrame:
    """Placeholder for a frame that could not be decoded."""

    reason: str


@dataclass(frozen=True, slots=True)
class SourceSpec:
    """Where frames come from.

    Attributes:
        path: folder, video file, `.mcap` file or camera file (MRAW: its .cih/.cihx or .mraw).
        kind: "folder", "video", "mcap", "mraw", "cine" or "tiff".
        topic: MCAP image topic (resolved when the source is opened).
        suffixes: image file suffixes a folder source reads (lower case, name order).
        reference_topic: MCAP image topic holding the reference image (the sample unloaded,
            taken before the stages closed: a topic ending in `REFERENCE_SUFFIX`), or None.
    """

    path: str
    kind: str
    topic: str | None = None
    suffixes: tuple[str, ...] = PNG
    reference_topic: str | None = None


# an MCAP image topic with this ending holds the reference image (one message)
REFERENCE_SUFFIX = "reference_image"


# decoding -------------------------------------------------------------------------------------
def image_from_msg(msg) -> np.ndarray:
    """A `sensor_msgs/Image` (any object with height, width, step, encoding, is_bigendian and
    data) -> [h, w] (mono) or [h, w, c] (colour, BGR order) uint8/uint16 array.

    Mono images in native byte order are a view on the message buffer (no copy).

    Raises:
        ValueError: unsupported encoding or a data size that does not match the header.
    """
    enc = _ENCODINGS.get(msg.encoding)
    if enc is None:
        raise ValueError(f"unsupported image encoding {msg.encoding!r} "
                         f"({', '.join(_ENCODINGS)})")
    dtype, ch = enc
    dt = np.dtype(dtype).newbyteorder(">" if msg.is_bigendian else "<")
    try:
        data = np.frombuffer(msg.data, dtype=dt)
    except TypeError:  # a list of ints rather than a buffer
        data = np.frombuffer(bytes(msg.data), dtype=dt)
    row_items = msg.step // dt.itemsize
    if msg.height == 0 or row_items < msg.width * ch or data.size < msg.height * row_items:
        raise ValueError(f"image data ({data.size} values) does not fit {msg.height}x"
                         f"{msg.width}x{ch} with step {msg.step}")
    img = data[: msg.height * row_items].reshape(msg.height, row_items)[:, : msg.width * ch]
    img = img.reshape(msg.height, msg.width, ch) if ch > 1 else img
    if msg.encoding.startswith("rgb"):
        img = img[..., [2, 1, 0] + ([3] if ch == 4 else [])]
    return img.astype(dtype, copy=False)


def _grey(img: np.ndarray) -> np.ndarray:
    """Colour (BGR / BGRA) -> grey; refuses pixel types other than uint8 / uint16."""
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY if img.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
    if img.dtype not in (np.uint8, np.uint16):
        raise SourceError(f"unsupported pixel type {img.dtype}")
    return img


# opening --------------------------------------------------------------------------------------
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
        raise SourceError(f"{path}: not a readable MCAP file ({exc}); cut short? "
                          "`metarig recover` salvages what it can") from None
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


def _folder_files(path: Path, suffixes: tuple[str, ...]) -> list[Path]:
    return sorted(f for f in path.iterdir() if f.suffix.lower() in suffixes)


def _no_images(path: Path, suffixes: tuple[str, ...]) -> SourceError:
    if suffixes == PNG:
        return SourceError(f"{path}: folder holds no *.png images")
    return SourceError(f"{path}: no images ({', '.join(suffixes)}) found")


def _open_mcap(p: Path, topic: str | None) -> SourceSpec:
    if p.is_dir():  # a rosbag2 folder with one .mcap file
        files = sorted(p.glob("*.mcap"))
        if len(files) != 1:
            raise SourceError(f"{p}: expected one .mcap file in the folder, found {len(files)}")
        p = files[0]
    topics = _image_topics(p)
    refs = [t for t in topics if t.endswith(REFERENCE_SUFFIX)]
    reference = refs[0] if len(refs) == 1 and topics[refs[0]] else None
    if reference is not None and topic is None:
        topics.pop(reference)
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
    return SourceSpec(str(p), "mcap", topic, reference_topic=reference)


def _kind_of(p: Path) -> str:
    from tracking.camera_files import SUFFIXES

    if p.is_dir():
        return "folder"
    if p.suffix.lower() == ".mcap":
        return "mcap"
    if p.suffix.lower() in VIDEO_SUFFIXES:
        return "video"
    for kind, suffixes in SUFFIXES.items():
        if p.suffix.lower() in suffixes:
            return kind
    raise SourceError(f"{p}: not a folder, a video ({', '.join(VIDEO_SUFFIXES)}), .mcap or a "
                      "camera file (.cihx/.cih/.mraw, .cine, .tif)")


def camera_file(spec: SourceSpec):
    """The header of a camera-file source (`tracking.camera_files.CameraFile`): its size, frame
    count, bit depth and, where the file records them, frame rate and first frame number
    relative to the trigger.

    Raises:
        SourceError: the file cannot be read or does not match its header.
    """
    from tracking.camera_files import CameraFileError, open_camera_file

    if spec.kind not in CAMERA_FILE_KINDS:
        raise SourceError(f"{spec.path}: a {spec.kind} source is not a camera file")
    try:
        return open_camera_file(spec.kind, spec.path)
    except CameraFileError as exc:
        raise SourceError(str(exc)) from None
    except OSError as exc:
        raise SourceError(f"{spec.path}: cannot read ({exc.strerror or exc})") from None


def open_source(path: str | Path, topic: str | None = None, kind: str | None = None,
                suffixes: tuple[str, ...] = PNG) -> SourceSpec:
    """Identify a source and check that it can be read.

    Args:
        path: a folder of images, a video file, an `.mcap` recording or a camera file (MRAW
            by its .cihx/.cih/.mraw, .cine, multi-page .tif).
        topic: MCAP image topic; by default the only image topic, or the one ending in
            `image_raw` (a topic ending in `reference_image` is the reference, not a frame).
        kind: one of `KINDS` (default: from the path).
        suffixes: image file suffixes of a folder source (default: `*.png` only).

    Raises:
        SourceError: missing path, no frames, unknown type, ambiguous topic, or a camera file
            that does not match its header.
    """
    p = Path(path)
    if not p.exists():
        raise SourceError(f"{p}: no such file or folder")
    kind = kind or _kind_of(p)
    if kind in CAMERA_FILE_KINDS:
        spec = SourceSpec(str(p), kind)
        camera_file(spec)
        return spec
    if kind == "folder":
        if not p.is_dir() or not _folder_files(p, suffixes):
            raise _no_images(p, suffixes)
        return SourceSpec(str(p), "folder", suffixes=suffixes)
    if kind == "mcap":
        return _open_mcap(p, topic)
    if kind == "video":
        cap = cv2.VideoCapture(str(p))
        ok = cap.isOpened()
        cap.release()
        if not ok:
            raise SourceError(f"{p}: cannot open video")
        return SourceSpec(str(p), "video")
    raise SourceError(f"unknown source kind {kind!r} (one of: {', '.join(KINDS)})")


def count_frames(spec: SourceSpec) -> int | None:
    """Number of frames the source holds (video: as the container says; None if unknown)."""
    if spec.kind == "folder":
        return len(_folder_files(Path(spec.path), spec.suffixes))
    if spec.kind == "mcap":
        return _image_topics(Path(spec.path)).get(spec.topic or "", 0)
    if spec.kind in CAMERA_FILE_KINDS:
        return camera_file(spec).n_frames
    cap = cv2.VideoCapture(spec.path)
    n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
    cap.release()
    return n if n > 0 else None


# reading --------------------------------------------------------------------------------------
Item = tuple[int | None, np.ndarray | BadFrame]  # (own stamp in ns or None, frame)


def _folder(spec: SourceSpec) -> Iterator[Item]:
    for f in _folder_files(Path(spec.path), spec.suffixes):
        img = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
        yield None, (img if img is not None else BadFrame(f"{f.name}: cannot decode image"))


def _video(spec: SourceSpec) -> Iterator[Item]:
    cap = cv2.VideoCapture(spec.path)
    try:
        while True:
            ok, img = cap.read()
            if not ok:
                break
            yield None, img
    finally:
        cap.release()


def _mcap(spec: SourceSpec, topic: str | None = None) -> Iterator[Item]:
    with open(spec.path, "rb") as f:
        reader = _mcap_reader(f)
        messages = reader.iter_decoded_messages(topics=[topic or spec.topic], log_time_order=True)
        for _schema, _channel, message, decoded in messages:
            st = decoded.header.stamp
            ns = int(st.sec) * 1_000_000_000 + int(st.nanosec)
            try:
                yield ns, np.ascontiguousarray(image_from_msg(decoded))
            except ValueError as exc:
                yield ns, BadFrame(f"message at log time {message.log_time} ns: {exc}")


def _camera_file(spec: SourceSpec) -> Iterator[Item]:
    """A camera file's frames; a file that ends early (cut after it was opened) stops with
    `SourceError`, as an unreadable source does."""
    from tracking.camera_files import CameraFileError, camera_frames

    frames = camera_frames(spec.kind, camera_file(spec))
    try:
        for img in frames:
            yield None, img
    except CameraFileError as exc:
        raise SourceError(str(exc)) from None


def _items(spec: SourceSpec) -> Iterator[Item]:
    if spec.kind in CAMERA_FILE_KINDS:
        return _camera_file(spec)
    return {"folder": _folder, "video": _video, "mcap": _mcap}[spec.kind](spec)


def recorded_reference(spec: SourceSpec) -> np.ndarray | None:
    """The source's own reference image (`SourceSpec.reference_topic`, its last message), or
    None when it holds none.

    Raises:
        SourceError: it is there but cannot be decoded.
    """
    if spec.kind != "mcap" or spec.reference_topic is None:
        return None
    last = None
    for _, item in _mcap(spec, spec.reference_topic):
        last = item
    if isinstance(last, BadFrame):
        raise SourceError(f"{spec.path}: the reference image ({spec.reference_topic}) is "
                          f"unreadable: {last.reason}")
    return last


def iter_frames(spec: SourceSpec) -> Iterator[tuple[int, np.ndarray | BadFrame]]:
    """Frames of the source in order: (k, image or BadFrame), k = 0, 1, ..."""
    for k, (_, item) in enumerate(_items(spec)):
        yield k, item


def replay_frames(spec: SourceSpec, fps: float) -> Iterator[tuple[int, np.ndarray]]:
    """Grey frames [h, w] uint8/uint16 with their time t_ns from the first frame (MCAP: the
    header stamps; folder, video: k / fps).

    Raises:
        SourceError: at the first frame that cannot be decoded, or when the source is empty.
    """
    t0, k = None, 0
    for k, (ns, item) in enumerate(_items(spec)):
        if isinstance(item, BadFrame):
            raise SourceError(f"{spec.path}: frame {k}: {item.reason}")
        if ns is None:
            ns = round(k * 1e9 / fps)
        t0 = ns if t0 is None else t0
        yield ns - t0, _grey(item)
    if t0 is None:
        raise SourceError(f"{spec.path}: no frames")


def mcap_frames(path: str | Path, topic: str) -> Iterator[tuple[int, np.ndarray]]:
    """`replay_frames` of one image topic of an MCAP recording, by header stamp."""
    return replay_frames(open_source(path, topic, kind="mcap"), fps=1.0)


def pattern_frames(width: int, height: int, fps: float, n: int = 0,
                   seed: int = 0) -> Iterator[tuple[int, np.ndarray]]:
    """A moving random texture (cheap: rolled copies of one noise image); n = 0 is endless.

    Frame k is the base texture rolled by k pixels, and its first two pixels hold k (16 bit),
    so a receiver can check every frame's identity. Yields (t_ns = k / fps, [height, width]
    uint8 frame).
    """
    base = np.random.default_rng(seed).integers(0, 256, (height, width + 1024), np.uint8)
    k = 0
    while n == 0 or k < n:
        s = k % 1024
        f = np.ascontiguousarray(base[:, s: s + width])
        f[0, 0], f[0, 1] = k & 0xFF, (k >> 8) & 0xFF
        yield round(k * 1e9 / fps), f
        k += 1


def open_replay(kind: str, path: str, fps: float, width: int, height: int, n: int,
                image_topic: str, seed: int = 0) -> Iterator[tuple[int, np.ndarray]]:
    """The camera node's replay: (t_ns, grey frame) of a configured source.

    Args:
        kind: "pattern" (synthetic: width x height, n frames, 0 endless, seeded), "folder"
            (any of `IMAGE_SUFFIXES`, name order), "video" or "mcap" (`image_topic`).
        path: the folder, video or recording (not used by "pattern").
        fps: frame rate of pattern, folder and video sources, Hz.

    Raises:
        SourceError: unknown kind, missing path or a source that cannot be opened.
    """
    if kind == "pattern":
        return pattern_frames(width, height, fps, n, seed)
    if kind not in KINDS:
        raise SourceError(f"unknown source {kind!r}")
    if not path:
        raise SourceError(f"source {kind!r} needs a path")
    return replay_frames(open_source(path, image_topic, kind, IMAGE_SUFFIXES), fps)
