"""Write `tests/data/tiny.cine`, a small Phantom CINE file, byte by byte from the format.

No library writes CINE files (pycine reads them only), so the test sample is built here from
the layout of the Vision Research "Cine File Format" document: a CINEFILEHEADER (44 bytes), a
BITMAPINFOHEADER (40 bytes), a SETUP block (12432 bytes, the size of the current SETUP
structure; the fields set here are at their documented offsets: FrameRate16 0, Mark "ST" 140,
Length 142, ImWidth 737, ImHeight 739, FrameRate 768, RealBPP 896, BlackLevel 5732,
WhiteLevel 5736), the table of 64-bit image offsets, and each image after an 8-byte
annotation block (AnnotationSize = 8, ImageSize), rows bottom-up, 16-bit little-endian.

The images: frames 0-5 of `recordings/focusing-12x8` (its first frame 25 ms after the
trigger, 1000 fps), rows 40-71 and columns 0-47, scaled x16 into 12 significant bits. Run from
the repository root: `.venv/bin/python tests/data/make_tiny_cine.py`.
"""

import struct
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
OUT = Path(__file__).with_name("tiny.cine")
FPS, FIRST_IMAGE_NO, N = 1000, 25, 6
ROWS, COLS = slice(40, 72), slice(0, 48)
SETUP_SIZE = 12432


def frames() -> np.ndarray:
    """[N, 32, 48] uint16: the crop of the sample recording's first frames, x16."""
    sys.path.insert(0, str(ROOT))
    from tracking.frame_sources import mcap_frames

    out = []
    for _t, f in mcap_frames(ROOT / "recordings/focusing-12x8/recording.mcap",
                             "/camera/image_raw"):
        out.append(f[ROWS, COLS].astype(np.uint16) * 16)
        if len(out) == N:
            break
    return np.stack(out)


def cine_bytes(images: np.ndarray, fps: int, first_image_no: int) -> bytes:
    n, h, w = images.shape
    off_bitmap, off_setup = 44, 44 + 40
    off_offsets = off_setup + SETUP_SIZE
    off_first = off_offsets + 8 * n
    image_bytes = w * h * 2
    header = struct.pack("<2sHHHiIiIIIIII", b"CI", 44, 0, 1, first_image_no, n, first_image_no,
                         n, off_bitmap, off_setup, off_offsets, 0, 0)
    bitmap = struct.pack("<IiiHHIIiiII", 40, w, h, 1, 16, 0, image_bytes, 0, 0, 0, 0)
    setup = bytearray(SETUP_SIZE)
    struct.pack_into("<H", setup, 0, fps)  # FrameRate16
    setup[140:142] = b"ST"  # Mark
    struct.pack_into("<H", setup, 142, SETUP_SIZE)  # Length
    struct.pack_into("<HH", setup, 737, w, h)  # ImWidth, ImHeight
    struct.pack_into("<I", setup, 768, fps)  # FrameRate
    struct.pack_into("<I", setup, 896, 12)  # RealBPP
    struct.pack_into("<II", setup, 5732, 0, 4095)  # BlackLevel, WhiteLevel
    stride = 8 + image_bytes
    offsets = struct.pack(f"<{n}q", *(off_first + k * stride for k in range(n)))
    body = b"".join(struct.pack("<II", 8, image_bytes)
                    + np.ascontiguousarray(img[::-1], "<u2").tobytes() for img in images)
    return header + bitmap + bytes(setup) + offsets + body


if __name__ == "__main__":
    OUT.write_bytes(cine_bytes(frames(), FPS, FIRST_IMAGE_NO))
    print(f"wrote {OUT} ({OUT.stat().st_size} bytes)")
