"""Camera frames that Rerun shows as images: a lossless PNG `CompressedImage` next to the raw frame.

Rerun (0.41) decodes `sensor_msgs/msg/Image` by its `encoding` alone: every single-channel
encoding (`mono8`, `mono16`, `8UC1`, `16UC1`, ...) becomes a `DepthImage` (depth colormap, back-
projected in 3D under a pinhole), whatever the header, frame_id or channel metadata say. A
`sensor_msgs/msg/CompressedImage` whose format is neither RVL depth nor `h264` becomes an
`EncodedImage`, decoded by its bytes (PNG signature), so a greyscale PNG shows as a greyscale
image. The recorder therefore writes, beside the unchanged raw `/camera/image_raw` stream, a
`/camera/image_raw/compressed` stream in the `image_transport` "compressed" convention
(format `"mono8; png compressed "`), optionally decimated in stamp time (`FramePreview`).

Pure (no rclpy, no I/O) except `add_previews`, which rewrites a finished recording through
`mcap_append`. The PNG encoder is zlib only (filter type None: on speckle it beats the adaptive
filters; see the module's report), so it needs neither OpenCV nor Pillow.
"""

import struct
import zlib
from pathlib import Path

import numpy as np

from ros_nodes import topics as T
from ros_nodes.logic.cdr import GREY_ENCODINGS, compressed_image_cdr, parse_image

PREVIEW_SUFFIX = "/compressed"  # image_transport's topic for the "compressed" transport
PREVIEW_TYPE = "sensor_msgs/msg/CompressedImage"
IMAGE_TYPE = "sensor_msgs/msg/Image"

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def preview_topic(image_topic: str) -> str:
    """`/camera/image_raw` -> `/camera/image_raw/compressed`."""
    return image_topic.rstrip("/") + PREVIEW_SUFFIX


def png_format(encoding: str) -> str:
    """The `CompressedImage.format` that `compressed_image_transport` writes for a PNG of a
    non-colour image: `"<encoding>; png compressed "` (the target encoding is left empty)."""
    return f"{encoding}; png compressed "


# ---------------------------------------------------------------------------------------- PNG


def _chunk(kind: bytes, payload: bytes) -> bytes:
    return b"".join((struct.pack(">I", len(payload)), kind, payload,
                     struct.pack(">I", zlib.crc32(payload, zlib.crc32(kind)) & 0xFFFFFFFF)))


def encode_png(frame: np.ndarray, level: int = 1) -> bytes:
    """Lossless greyscale PNG of a 2-D uint8 or uint16 array (zlib `level` 0-9; 1: fast).

    Every row uses filter type 0 (None): speckle frames are close to white noise, where the
    predictive filters (Sub, Up, Paeth) only add entropy.
    """
    f = np.asarray(frame)
    if f.ndim != 2 or f.dtype not in (np.uint8, np.uint16) or 0 in f.shape:
        raise ValueError(f"need a non-empty 2-D uint8/uint16 frame, got {f.dtype} {f.shape}")
    h, w = f.shape
    bits = 8 * f.dtype.itemsize
    rows = np.ascontiguousarray(f, dtype=">u2" if bits == 16 else np.uint8).view(np.uint8)
    raw = np.zeros((h, rows.shape[1] + 1), np.uint8)  # leading 0 per row: filter type None
    raw[:, 1:] = rows.reshape(h, -1)
    ihdr = struct.pack(">IIBBBBB", w, h, bits, 0, 0, 0, 0)  # colour type 0: greyscale
    return b"".join((_PNG_SIGNATURE, _chunk(b"IHDR", ihdr),
                     _chunk(b"IDAT", zlib.compress(raw.data, level)), _chunk(b"IEND", b"")))


def decode_png(png: bytes) -> np.ndarray:
    """Inverse of `encode_png` for its own output (greyscale, 8/16 bit, filter None, no
    interlace); for tests and tools. Raises ValueError on anything else."""
    if png[:8] != _PNG_SIGNATURE:
        raise ValueError("not a PNG")
    pos, idat, ihdr = 8, [], None
    while pos < len(png):
        (n,) = struct.unpack_from(">I", png, pos)
        kind, payload = png[pos + 4:pos + 8], png[pos + 8:pos + 8 + n]
        pos += 12 + n
        if kind == b"IHDR":
            ihdr = struct.unpack(">IIBBBBB", payload)
        elif kind == b"IDAT":
            idat.append(payload)
        elif kind == b"IEND":
            break
    if ihdr is None or ihdr[3] != 0 or ihdr[2] not in (8, 16) or ihdr[6] != 0:
        raise ValueError(f"unsupported PNG header {ihdr}")
    w, h, bits = ihdr[:3]
    raw = np.frombuffer(zlib.decompress(b"".join(idat)), np.uint8).reshape(h, -1)
    if np.any(raw[:, 0] != 0):
        raise ValueError("PNG rows use a filter other than None")
    pix = raw[:, 1:].copy()
    return pix.view(">u2").astype(np.uint16) if bits == 16 else pix.reshape(h, w)


# ----------------------------------------------------------------------------- frame -> preview


def compressed_frame(image: bytes | memoryview | np.ndarray, stamp_ns: int | None = None, *,
                     frame_id: str = "camera", level: int = 1) -> bytes:
    """The CDR of a `sensor_msgs/CompressedImage` holding a lossless PNG of one grey frame.

    `image` is either the CDR of a `sensor_msgs/Image` (mono8/8UC1/mono16/16UC1; its stamp and
    frame_id are kept unless `stamp_ns` is given) or a 2-D uint8/uint16 array (then `stamp_ns`
    is required). The format string is `"<encoding>; png compressed "`, as
    `compressed_image_transport` writes it, so ROS tools decode it too.
    """
    if isinstance(image, np.ndarray):
        if stamp_ns is None:
            raise ValueError("stamp_ns is required for an array frame")
        enc = {np.dtype(np.uint8): "mono8", np.dtype(np.uint16): "mono16"}.get(image.dtype)
        if enc is None:
            raise ValueError(f"frames must be uint8 or uint16, got {image.dtype}")
        return compressed_image_cdr(stamp_ns, frame_id, png_format(enc), encode_png(image, level))
    msg = parse_image(image)
    png = encode_png(msg.pixels(), level)
    return compressed_image_cdr(msg.stamp_ns if stamp_ns is None else stamp_ns, msg.frame_id,
                                png_format(msg.encoding), png)


class FramePreview:
    """Decides which raw frames get a PNG twin, by header stamp: at most one per
    `min_period_ns` (0: every frame). Pure logic; the recorder calls `offer` for each frame of
    the raw topic and writes what it returns (None: no preview for this frame).

    Decimating by stamp (not by arrival) keeps the choice deterministic for replays and for a
    camera that downloads its footage after the event. A stamp that goes backwards (a new take,
    a restarted camera) restarts the clock.
    """

    def __init__(self, min_period_ns: int = 0, *, level: int = 1):
        if min_period_ns < 0:
            raise ValueError("min_period_ns must be >= 0")
        self.min_period_ns = int(min_period_ns)
        self.level = level
        self._last: int | None = None
        self.offered = 0
        self.made = 0

    def due(self, stamp_ns: int) -> bool:
        """Whether a frame stamped `stamp_ns` gets a preview (updates the clock if so)."""
        self.offered += 1
        if (self._last is None or stamp_ns < self._last
                or stamp_ns - self._last >= self.min_period_ns):
            self._last = stamp_ns
            return True
        return False

    def offer(self, image_cdr: bytes) -> bytes | None:
        """The CompressedImage CDR for this raw frame, or None when it is skipped or is not a
        grey 8/16-bit frame (colour encodings are already shown as images by Rerun)."""
        msg = parse_image(image_cdr)
        if msg.encoding not in GREY_ENCODINGS or not self.due(msg.stamp_ns):
            return None
        self.made += 1
        return compressed_image_cdr(msg.stamp_ns, msg.frame_id, png_format(msg.encoding),
                                    encode_png(msg.pixels(), self.level))


# ------------------------------------------------------------------------ finished recordings


def preview_messages(src: str | Path, image_topic: str = T.IMAGE.name, *,
                     min_period_ns: int = 0, level: int = 1) -> list:
    """The PNG previews (`mcap_append.NewMessage`s on `preview_topic(image_topic)`) of the raw
    frames of a finished recording."""
    from mcap.reader import make_reader

    from ros_nodes.logic.mcap_append import NewMessage

    preview = FramePreview(min_period_ns, level=level)
    topic, out = preview_topic(image_topic), []
    with open(src, "rb") as f:
        for _schema, _channel, msg in make_reader(f).iter_messages(topics=[image_topic],
                                                                   log_time_order=True):
            cdr = preview.offer(msg.data)
            if cdr is not None:
                out.append(NewMessage(topic, msg.log_time, cdr))
    return out


def add_previews(src: str | Path, dst: str | Path, image_topic: str = T.IMAGE.name, *,
                 min_period_ns: int = 0, level: int = 1) -> int:
    """Write `dst` = `src` + a PNG preview stream of `image_topic` (replacing an earlier one);
    for recordings made before the recorder wrote previews. Returns the number of previews."""
    from ros_nodes.logic.mcap_append import append_messages

    out = preview_messages(src, image_topic, min_period_ns=min_period_ns, level=level)
    topic = preview_topic(image_topic)
    append_messages(src, dst, {topic: PREVIEW_TYPE}, out, replace=(topic,))
    return len(out)


def depth_as_image_lenses() -> list:
    """Rerun lenses that re-label the `DepthImage` Rerun makes of grey frames as an `Image`
    (same buffer; the format Rerun derives from mono8/mono16 already carries the L colour
    model). For `to_rrd`, or for a Python user of `rerun.chunk.McapReader(...).stream()`; a
    viewer opening the MCAP itself does not apply them (that is what the PNG stream is for)."""
    import rerun as rr
    from rerun.chunk import DeriveLens

    return [DeriveLens("DepthImage:buffer").to_component(rr.Image.descriptor_buffer(), "."),
            DeriveLens("DepthImage:format").to_component(rr.Image.descriptor_format(), ".")]


def to_rrd(src: str | Path, dst: str | Path, *, application_id: str = "metarig",
           recording_id: str | None = None) -> Path:
    """Convert an MCAP recording to an `.rrd` in which the raw grey frames are `Image`s
    (everything else as Rerun's MCAP importer makes it). Needs no preview stream."""
    from rerun.chunk import McapReader

    src, dst = Path(src), Path(dst)
    stream = McapReader(src).stream().lenses(depth_as_image_lenses(),
                                             output_mode="forward_unmatched")
    stream.write_rrd(dst, application_id=application_id,
                     recording_id=recording_id or src.parent.name or src.stem)
    return dst
