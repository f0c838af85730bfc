"""Frame sources for the camera node: MCAP replay, image folder, video file, test pattern.

Each source yields `(t_ns, frame)` with t_ns the capture time relative to the first frame (ns)
and frame a 2-D uint8/uint16 array. Pure: MCAP images are decoded with `rosbags` (no rclpy).
"""

from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".bmp", ".jpg", ".jpeg", ".pgm")


class SourceError(ValueError):
    """A replay source that cannot be opened or decoded (the message says why)."""


def _mono(img: np.ndarray) -> np.ndarray:
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    if img.dtype not in (np.uint8, np.uint16):
        raise SourceError(f"unsupported pixel type {img.dtype}")
    return img


def folder_frames(path: str | Path, fps: float) -> Iterator[tuple[int, np.ndarray]]:
    """Images of a folder in name order, at `fps`."""
    files = sorted(p for p in Path(path).iterdir() if p.suffix.lower() in IMAGE_SUFFIXES) \
        if Path(path).is_dir() else []
    if not files:
        raise SourceError(f"{path}: no images ({', '.join(IMAGE_SUFFIXES)}) found")
    for k, f in enumerate(files):
        img = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise SourceError(f"{f}: cannot decode image")
        yield int(round(k * 1e9 / fps)), _mono(img)


def video_frames(path: str | Path, fps: float | None = None) -> Iterator[tuple[int, np.ndarray]]:
    """Frames of a video file (its own frame rate unless `fps` is given)."""
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise SourceError(f"{path}: cannot open video")
    rate = fps or cap.get(cv2.CAP_PROP_FPS) or 30.0
    k = 0
    try:
        while True:
            ok, img = cap.read()
            if not ok:
                break
            yield int(round(k * 1e9 / rate)), _mono(img)
            k += 1
    finally:
        cap.release()
    if k == 0:
        raise SourceError(f"{path}: no frames")


def mcap_frames(path: str | Path, topic: str) -> Iterator[tuple[int, np.ndarray]]:
    """`sensor_msgs/Image` frames of one topic of an MCAP (or rosbag2) recording, by stamp."""
    from rosbags.highlevel import AnyReader

    p = Path(path)
    if not p.exists():
        raise SourceError(f"{p}: no such recording")
    try:
        reader = AnyReader([p])
        reader.open()
    except Exception as e:  # noqa: BLE001 - rosbags raises several unrelated types
        raise SourceError(f"{p}: not a readable recording ({e})") from e
    try:
        cons = [c for c in reader.connections if c.topic == topic]
        if not cons:
            topics = sorted({c.topic for c in reader.connections})
            raise SourceError(f"{p}: no topic {topic!r} (has: {', '.join(topics)})")
        t0 = None
        for con, _, raw in reader.messages(connections=cons):
            m = reader.deserialize(raw, con.msgtype)
            t = m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec
            t0 = t if t0 is None else t0
            dt = {"mono8": np.uint8, "mono16": np.uint16}.get(m.encoding)
            if dt is None:
                raise SourceError(f"{p}: unsupported encoding {m.encoding!r}")
            a = np.frombuffer(bytes(m.data), np.dtype(dt).newbyteorder(">" if m.is_bigendian
                                                                          else "<"))
            yield t - t0, a.reshape(m.height, -1)[:, : m.width]
    finally:
        reader.close()


def pattern_frames(width: int, height: int, fps: float, n: int = 0,
                   seed: int = 0) -> Iterator[tuple[int, np.ndarray]]:
    """A moving random texture (cheap: rolled copies of one noise image); n = 0 is endless.

    Frame k is the base texture rolled by k pixels, and its first two pixels hold k (16 bit),
    so a receiver can check every frame's identity.
    """
    base = np.random.default_rng(seed).integers(0, 256, (height, width + 1024), np.uint8)
    k = 0
    while n == 0 or k < n:
        s = k % 1024
        f = np.ascontiguousarray(base[:, s: s + width])
        f[0, 0], f[0, 1] = k & 0xFF, (k >> 8) & 0xFF
        yield int(round(k * 1e9 / fps)), f
        k += 1


def open_source(kind: str, path: str, fps: float, width: int, height: int, n: int,
                image_topic: str, seed: int = 0) -> Iterator[tuple[int, np.ndarray]]:
    """The frame iterator for a configured replay source."""
    if kind == "pattern":
        return pattern_frames(width, height, fps, n, seed)
    if not path:
        raise SourceError(f"source {kind!r} needs a path")
    if kind == "folder":
        return folder_frames(path, fps)
    if kind == "video":
        return video_frames(path, fps)
    if kind == "mcap":
        return mcap_frames(path, image_topic)
    raise SourceError(f"unknown source {kind!r}")
