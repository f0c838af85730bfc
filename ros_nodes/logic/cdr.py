"""Hand-built CDR (XCDR1, little-endian): every serialized message the project reads or writes
without message objects, in one place (no rclpy).

The camera's hot path: a 640x480 frame published as a `sensor_msgs/Image` object costs three
copies in Python (bytes -> array.array, -> C struct, -> serialized buffer); building the
serialized message directly costs one (`ImageEncoder`, `restamp`). The recorder reads header
stamps and `std_msgs/String` texts of the messages it writes (`header_stamp_ns`,
`string_text`); the Rerun previews decode images and build `CompressedImage`s (`parse_image`,
`compressed_image_cdr`). Checked byte for byte against rclpy's serializer in tests/ros.
"""

import struct
from dataclasses import dataclass

import numpy as np

ENC_HEADER = b"\x00\x01\x00\x00"  # CDR little-endian, no options
STAMP = struct.Struct("<iI")  # builtin_interfaces/Time, right after the 4-byte header
_U32 = struct.Struct("<I")
# encodings PNG stores losslessly as greyscale (8 or 16 bit); Rerun shows the raw ones as depth
GREY_ENCODINGS = {"mono8": 8, "8UC1": 8, "mono16": 16, "16UC1": 16}


def pack_stamp(ns: int) -> bytes:
    """A `builtin_interfaces/Time` of `ns` nanoseconds."""
    ns = int(ns)
    return STAMP.pack(ns // 1_000_000_000, ns % 1_000_000_000)


def header_stamp_ns(cdr: bytes) -> int | None:
    """The `header.stamp` of a little-endian CDR message whose first field is a Header."""
    if len(cdr) < 12 or cdr[1] != 0x01:  # 0x0001: CDR little-endian
        return None
    sec, nsec = STAMP.unpack_from(cdr, 4)
    return sec * 1_000_000_000 + nsec


def string_text(cdr: bytes) -> str | None:
    """The text of a serialized `std_msgs/String`, or None if malformed."""
    if len(cdr) < 8 or cdr[1] != 0x01:
        return None
    (n,) = _U32.unpack_from(cdr, 4)
    if n == 0 or 8 + n > len(cdr):
        return None
    return cdr[8: 8 + n - 1].decode("utf-8", errors="replace")


def _string(s: str) -> bytes:
    """A CDR string: uint32 length with the NUL, the bytes, the NUL (to be placed 4-aligned)."""
    b = s.encode() + b"\x00"
    return _U32.pack(len(b)) + b


def _pad(n: int) -> bytes:
    return b"\x00" * ((-n) % 4)


def _read_string(buf: memoryview, pos: int) -> tuple[str, int]:
    """A CDR string at body offset `pos` (4-aligned): its text and the offset after it."""
    (n,) = _U32.unpack_from(buf, 4 + pos)
    if n == 0 or 4 + pos + 4 + n > len(buf):
        raise ValueError("malformed CDR string")
    text = bytes(buf[4 + pos + 4: 4 + pos + 4 + n - 1]).decode()
    return text, pos + 4 + n


def _align(pos: int, n: int = 4) -> int:
    return pos + (-pos) % n


class ImageEncoder:
    """Serialized `sensor_msgs/Image` for frames of one shape/encoding/frame_id.

    The part after the stamp is computed once; `encode(ns, frame)` is one join of the stamp,
    that prefix and the pixel bytes.
    """

    def __init__(self, height: int, width: int, dtype, frame_id: str = "camera"):
        dt = np.dtype(dtype)
        self.encoding = {np.dtype(np.uint8): "mono8", np.dtype(np.uint16): "mono16"}.get(dt)
        if self.encoding is None:
            raise ValueError(f"frames must be uint8 or uint16, got {dt}")
        self.shape, self.dtype = (int(height), int(width)), dt.newbyteorder("<")
        step = int(width) * dt.itemsize
        body = bytearray()
        pos = 8  # offsets count from the end of the 4-byte encapsulation header; stamp = 8
        body += _string(frame_id)
        body += _pad(pos + len(body))
        body += struct.pack("<II", height, width)
        body += _string(self.encoding)
        body += b"\x00"  # is_bigendian
        body += _pad(pos + len(body))
        body += struct.pack("<II", step, step * int(height))
        self._prefix = bytes(body)

    def encode(self, ns: int, frame: np.ndarray) -> bytes:
        if frame.shape != self.shape or frame.dtype != self.dtype:
            raise ValueError(f"frame {frame.dtype} {frame.shape} does not match the encoder "
                             f"({self.dtype} {self.shape})")
        ns = int(ns)
        return b"".join((ENC_HEADER, pack_stamp(ns), self._prefix,
                         memoryview(np.ascontiguousarray(frame)).cast("B")))


def restamp(cdr: bytes, ns: int) -> bytes:
    """A serialized stamped message (first field a Header) with its stamp replaced."""
    return b"".join((cdr[:4], pack_stamp(ns), cdr[12:]))


@dataclass(frozen=True)
class RawImage:
    """A decoded `sensor_msgs/Image` (pixel bytes are a view into the CDR buffer)."""

    stamp_ns: int
    frame_id: str
    height: int
    width: int
    encoding: str
    is_bigendian: bool
    step: int
    data: memoryview

    def pixels(self) -> np.ndarray:
        """The frame as a (height, width) array of a grey encoding (row padding dropped)."""
        bits = GREY_ENCODINGS.get(self.encoding)
        if bits is None:
            raise ValueError(f"not a single-channel 8/16-bit encoding: {self.encoding!r}")
        dtype = np.dtype(np.uint8 if bits == 8 else (">u2" if self.is_bigendian else "<u2"))
        row = self.width * dtype.itemsize
        if self.step < row or len(self.data) < self.step * (self.height - 1) + row:
            raise ValueError(f"image data too short: step {self.step}, {len(self.data)} bytes "
                             f"for {self.width}x{self.height} {self.encoding}")
        buf = np.frombuffer(self.data, np.uint8)
        rows = np.lib.stride_tricks.as_strided(buf, (self.height, row), (self.step, 1))
        return np.ascontiguousarray(rows).view(dtype).reshape(self.height, self.width)


def parse_image(cdr: bytes | memoryview) -> RawImage:
    """Decode a little-endian CDR `sensor_msgs/Image` without copying the pixels."""
    buf = memoryview(cdr).cast("B") if not isinstance(cdr, memoryview) else cdr.cast("B")
    if len(buf) < 12 or buf[1] != 0x01:
        raise ValueError("not a little-endian CDR message")
    sec, nsec = STAMP.unpack_from(buf, 4)
    frame_id, pos = _read_string(buf, 8)
    pos = _align(pos)
    height, width = struct.unpack_from("<II", buf, 4 + pos)
    encoding, pos = _read_string(buf, pos + 8)
    bigendian = bool(buf[4 + pos])
    pos = _align(pos + 1)
    step, n = struct.unpack_from("<II", buf, 4 + pos)
    start = 4 + pos + 8
    if start + n > len(buf):
        raise ValueError(f"image data truncated: {n} bytes announced, {len(buf) - start} present")
    return RawImage(sec * 1_000_000_000 + nsec, frame_id, height, width, encoding, bigendian,
                    step, buf[start:start + n])


def compressed_image_cdr(stamp_ns: int, frame_id: str, fmt: str, data: bytes) -> bytes:
    """A little-endian CDR `sensor_msgs/CompressedImage` (header, format, data)."""
    body = bytearray(pack_stamp(stamp_ns))
    body += _string(frame_id)
    body += _pad(len(body))
    body += _string(fmt)
    body += _pad(len(body))
    body += _U32.pack(len(data))
    return b"".join((ENC_HEADER, bytes(body), data))


class _Body:
    """A CDR body under construction: offsets count from the end of the encapsulation header,
    each primitive aligned to its own size (XCDR1)."""

    def __init__(self):
        self.buf = bytearray()

    def align(self, n: int) -> None:
        self.buf += b"\x00" * ((-len(self.buf)) % n)

    def u32(self, *values: int) -> None:
        self.align(4)
        self.buf += struct.pack(f"<{len(values)}I", *values)

    def string(self, s: str) -> None:
        self.align(4)
        self.buf += _string(s)

    def doubles(self, values, sequence: bool = True) -> None:
        """float64 values: a sequence (with its count) or a fixed-size array."""
        a = np.asarray(values, "<f8").ravel()
        if sequence:
            self.u32(a.size)
        self.align(8)  # even before no element, as Fast-CDR does
        self.buf += a.tobytes()

    def header(self, ns: int, frame_id: str) -> None:
        self.buf += pack_stamp(ns)
        self.string(frame_id)

    def cdr(self) -> bytes:
        return ENC_HEADER + bytes(self.buf)


def joint_state_cdr(ns: int, names, positions, velocities=(), frame_id: str = "") -> bytes:
    """A little-endian CDR `sensor_msgs/JointState` (no effort), lengths m, speeds m/s."""
    b = _Body()
    b.header(ns, frame_id)
    b.u32(len(names))
    for n in names:
        b.string(n)
    b.doubles(positions)
    b.doubles(velocities)
    b.doubles(())
    return b.cdr()


def camera_info_cdr(ns: int, width: int, height: int, m_per_px: float,
                    frame_id: str = "camera") -> bytes:
    """A little-endian CDR `sensor_msgs/CameraInfo` of the square-on camera, as the camera node
    sends it (`ros_nodes.convert.camera_info`): K holds f = 1 / m_per_px, no distortion."""
    f = 1.0 / m_per_px
    cx, cy = (width - 1) / 2.0, (height - 1) / 2.0
    b = _Body()
    b.header(ns, frame_id)
    b.u32(height, width)
    b.string("plumb_bob")
    b.doubles([0.0] * 5)
    b.doubles([f, 0.0, cx, 0.0, f, cy, 0.0, 0.0, 1.0], sequence=False)
    b.doubles([1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0], sequence=False)
    b.doubles([f, 0.0, cx, 0.0, 0.0, f, cy, 0.0, 0.0, 0.0, 1.0, 0.0], sequence=False)
    b.u32(0, 0)  # binning
    b.u32(0, 0, 0, 0)  # roi x_offset, y_offset, height, width
    b.buf += b"\x00"  # roi do_rectify
    return b.cdr()


def string_cdr(text: str) -> bytes:
    """A little-endian CDR `std_msgs/String`."""
    b = _Body()
    b.string(text)
    return b.cdr()
