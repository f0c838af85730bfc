"""High-speed camera files: Photron MRAW (+ CIH/CIHX), Phantom CINE and TIFF stacks.

One reader per format: `open_*` reads the header and checks the file against it (size,
pixel layout) without reading a frame; `*_frames` yields the frames one at a time, grey
[height, width] uint8 or uint16, so a file larger than memory streams. `tracking.frame_sources`
routes its `mraw`, `cine` and `tiff` sources here. The header's frame rate and the number of
the first frame relative to the trigger (frame 0) are kept where the format records them, so
an import can place the frames on the trigger's clock.

- MRAW: the header is the `.cihx` (XML) or `.cih` (text) beside the `.mraw`, read with
  `pyMRAW` (module of the `pymraw` package); frames are consecutive, 8 or 16 bit little-endian
  or 12 bit packed (two pixels in three bytes, high bits first).
- CINE (Vision Research): CINEFILEHEADER, BITMAPINFOHEADER, SETUP (frame rate at byte 768,
  RealBPP at 896) and a table of 64-bit image offsets; each image is preceded by its
  annotation block (`AnnotationSize` bytes, ending with the image size). Uncompressed grey 8 or
  16 bit is read; rows are stored bottom-up when the bitmap height is positive.
- TIFF: every page of one multi-page file (`tifffile`); an ImageJ stack's `finterval` gives
  the frame rate.
"""

import re
import struct
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

MRAW_SUFFIXES = (".mraw", ".cih", ".cihx")
CINE_SUFFIXES = (".cine",)
TIFF_SUFFIXES = (".tif", ".tiff")


class CameraFileError(ValueError):
    """A camera file that cannot be read, or that does not match its header (one line)."""


@dataclass(frozen=True, slots=True)
class CameraFile:
    """What a camera file's header says.

    Attributes:
        path: the file the pixels are read from (.mraw, .cine, .tif).
        header: the file the header was read from (the .cih/.cihx of an MRAW; else `path`).
        width, height: frame size, px.
        n_frames: frames in the file.
        bits: stored bits per pixel (8, 12 packed, 16).
        fps: frame rate recorded in the file, Hz, or None.
        first_frame: number of the first frame relative to the trigger frame (0; negative:
            recorded before the trigger), or None where the file does not record it.
    """

    path: str
    header: str
    width: int
    height: int
    n_frames: int
    bits: int
    fps: float | None
    first_frame: int | None

    @property
    def frame_bytes(self) -> int:
        return self.width * self.height * self.bits // 8


def _positive(v) -> float | None:
    try:
        v = float(v)
    except (TypeError, ValueError):
        return None
    return v if np.isfinite(v) and v > 0 else None


# MRAW -----------------------------------------------------------------------------------------
def _sibling(p: Path, suffixes: tuple[str, ...]) -> Path | None:
    """The file beside `p` with the same stem and one of `suffixes` (any letter case)."""
    for s in suffixes:
        for f in (p.with_suffix(s), p.with_suffix(s.upper())):
            if f.is_file():
                return f
    return None


def open_mraw(path: str | Path) -> CameraFile:
    """The header of an MRAW recording given as its .mraw, .cih or .cihx file.

    Raises:
        CameraFileError: a missing half, an unreadable header, a pixel format other than mono
            8/12/16 bit, or an MRAW whose size differs from what the header announces.
    """
    import pyMRAW

    p = Path(path)
    if p.suffix.lower() == ".mraw":
        mraw, cih = p, _sibling(p, (".cihx", ".cih"))
        if cih is None:
            raise CameraFileError(f"{p}: no .cihx or .cih header beside it (copy it from the "
                                  "camera with the MRAW)")
    else:
        cih, mraw = p, _sibling(p, (".mraw",))
        if mraw is None:
            raise CameraFileError(f"{p}: no {p.stem}.mraw beside it")
    try:
        info = pyMRAW.get_cih(str(cih))
        width, height = int(info["Image Width"]), int(info["Image Height"])
        n, bits = int(info["Total Frame"]), int(info["Color Bit"])
        fmt = str(info.get("File Format", "mraw"))
    except Exception as exc:  # noqa: BLE001 - the XML/text parsers raise assorted types
        raise CameraFileError(f"{cih}: not a readable Photron header "
                              f"({type(exc).__name__}: {exc})") from None
    if fmt.lower() != "mraw":
        raise CameraFileError(f"{cih}: the header announces {fmt} images, not MRAW")
    if bits not in (8, 12, 16) or "color" in str(info.get("Color Type", "mono")).lower():
        raise CameraFileError(f"{cih}: {bits}-bit {info.get('Color Type', 'colour')} images; "
                              "mono 8, 12 or 16 bit MRAW is read")
    if min(width, height, n) < 1:
        raise CameraFileError(f"{cih}: announces {n} frames of {width}x{height} px")
    first = _cih_start_frame(cih, info)
    cam = CameraFile(str(mraw), str(cih), width, height, n, bits,
                     _positive(info.get("Record Rate(fps)")), first)
    size = mraw.stat().st_size
    want = n * cam.frame_bytes
    if size < want:
        raise CameraFileError(
            f"{mraw}: cut short: {size} bytes hold {size // cam.frame_bytes} whole frames of "
            f"the {n} its header {cih.name} announces ({width}x{height} px, {bits} bit); copy "
            "it from the camera again")
    if size != want:
        raise CameraFileError(
            f"{mraw}: {size} bytes do not match its header {cih.name} ({n} frames of "
            f"{width}x{height} px at {bits} bit = {want} bytes): a header of another recording?")
    return cam


def _cih_start_frame(cih: Path, info: dict) -> int | None:
    """The number of the first saved frame relative to the trigger ("Start Frame")."""
    if "Start Frame" in info:
        try:
            return int(info["Start Frame"])
        except (TypeError, ValueError):
            return None
    m = re.search(r"<startFrame>\s*(-?\d+)\s*</startFrame>",
                  cih.read_text(encoding="utf-8", errors="ignore"))
    return int(m.group(1)) if m else None


def _unpack12(buf: bytes, height: int, width: int) -> np.ndarray:
    """12-bit packed pixels (3 bytes: aaaaaaaa aaaabbbb bbbbbbbb) -> uint16 [height, width]."""
    b = np.frombuffer(buf, np.uint8).reshape(-1, 3).astype(np.uint16)
    out = np.empty((b.shape[0], 2), np.uint16)
    out[:, 0] = (b[:, 0] << 4) | (b[:, 1] >> 4)
    out[:, 1] = ((b[:, 1] & 0x0F) << 8) | b[:, 2]
    return out.reshape(height, width)


def mraw_frames(cam: CameraFile) -> Iterator[np.ndarray]:
    """The frames of an MRAW, one read at a time."""
    dtype = np.uint8 if cam.bits == 8 else np.dtype("<u2")
    with open(cam.path, "rb") as f:
        for _ in range(cam.n_frames):
            buf = f.read(cam.frame_bytes)
            if len(buf) < cam.frame_bytes:
                raise CameraFileError(f"{cam.path}: ends inside a frame (cut short)")
            if cam.bits == 12:
                yield _unpack12(buf, cam.height, cam.width)
            else:
                yield np.frombuffer(buf, dtype).reshape(cam.height, cam.width).astype(
                    dtype.newbyteorder("=") if cam.bits == 16 else dtype)


# CINE -----------------------------------------------------------------------------------------
CINE_HEADER = struct.Struct("<2sHHHiIiIIIIII")  # CINEFILEHEADER (TriggerTime as 2 x uint32)
BITMAP_HEADER = struct.Struct("<IiiHHIIiiII")  # BITMAPINFOHEADER
SETUP_FRAME_RATE = 768  # SETUP.FrameRate, uint32, fps
SETUP_REAL_BPP = 896  # SETUP.RealBPP, uint32: significant bits of a 16-bit pixel


def open_cine(path: str | Path) -> CameraFile:
    """The header of a Phantom CINE file (uncompressed grey 8 or 16 bit).

    Raises:
        CameraFileError: not a CINE file, a packed/colour format, or images beyond its end.
    """
    p = Path(path)
    size = p.stat().st_size
    try:
        with open(p, "rb") as f:
            head = f.read(CINE_HEADER.size + BITMAP_HEADER.size)
            (kind, _hsize, compression, _ver, _first_movie, _total, first_no, count, off_bmp,
             off_setup, off_images, _t0, _t1) = CINE_HEADER.unpack_from(head)
            if kind != b"CI":
                raise CameraFileError(f"{p}: not a CINE file (no 'CI' at its start)")
            f.seek(off_bmp)
            (_bsize, width, height, _planes, bpp, bcompr, _isize, _xppm, _yppm, _cu,
             _ci) = BITMAP_HEADER.unpack(f.read(BITMAP_HEADER.size))
            f.seek(off_setup + SETUP_FRAME_RATE)
            (fps,) = struct.unpack("<I", f.read(4))
            offsets = np.frombuffer(_read_at(f, off_images, 8 * count), "<i8")
    except struct.error:
        raise CameraFileError(f"{p}: cut short inside its header") from None
    except OSError as exc:
        raise CameraFileError(f"{p}: cannot read ({exc.strerror or exc})") from None
    if compression != 0 or bcompr != 0 or bpp not in (8, 16):
        raise CameraFileError(f"{p}: {bpp}-bit {'packed ' if bcompr else ''}images "
                              f"(compression {compression}); uncompressed grey 8 or 16 bit "
                              "CINE is read (save it so from the camera software)")
    cam = CameraFile(str(p), str(p), int(width), abs(int(height)), int(count), int(bpp),
                     _positive(fps), int(first_no))
    if count < 1 or offsets.size != count:
        raise CameraFileError(f"{p}: announces {count} images, its image table is cut short")
    if int(offsets.max()) + 8 + cam.frame_bytes > size:
        last = int(np.sum(offsets + 8 + cam.frame_bytes <= size))
        raise CameraFileError(f"{p}: cut short: {last} of its {count} images lie within its "
                              f"{size} bytes")
    return cam


def _read_at(f, offset: int, n: int) -> bytes:
    f.seek(offset)
    buf = f.read(n)
    if len(buf) < n:
        raise struct.error("short read")
    return buf


def cine_frames(cam: CameraFile) -> Iterator[np.ndarray]:
    """The images of a CINE file, one read at a time, top row first."""
    dtype = np.uint8 if cam.bits == 8 else np.dtype("<u2")
    with open(cam.path, "rb") as f:
        (_k, _h, _c, _v, _m, _t, _fn, count, off_bmp, _os, off_images, _a, _b) = \
            CINE_HEADER.unpack(f.read(CINE_HEADER.size))
        f.seek(off_bmp + 8)
        (signed_height,) = struct.unpack("<i", f.read(4))
        offsets = np.frombuffer(_read_at(f, off_images, 8 * count), "<i8")
        for off in offsets:
            (annotation,) = struct.unpack("<I", _read_at(f, int(off), 4))
            buf = _read_at(f, int(off) + annotation, cam.frame_bytes)
            img = np.frombuffer(buf, dtype).reshape(cam.height, cam.width)
            yield np.ascontiguousarray(img[::-1] if signed_height > 0 else img,
                                       dtype.newbyteorder("=") if cam.bits == 16 else dtype)


# TIFF -----------------------------------------------------------------------------------------
def open_tiff(path: str | Path) -> CameraFile:
    """The pages of a (multi-page) TIFF file, which must all be one grey size and type.

    Raises:
        CameraFileError: not a readable TIFF, or pages that are not 8/16-bit grey.
    """
    import tifffile

    p = Path(path)
    try:
        with tifffile.TiffFile(p) as tif:
            first = tif.pages.first
            n = len(tif.pages)
            shape, dtype = tuple(first.shape), np.dtype(first.dtype)
            ij = tif.imagej_metadata or {}
    except Exception as exc:  # noqa: BLE001 - tifffile raises assorted types on a bad file
        raise CameraFileError(f"{p}: not a readable TIFF ({type(exc).__name__}: {exc})") \
            from None
    if len(shape) != 2 or dtype not in (np.uint8, np.uint16):
        raise CameraFileError(f"{p}: pages are {dtype} {shape}; grey 8 or 16 bit pages are read")
    interval = _positive(ij.get("finterval"))
    return CameraFile(str(p), str(p), shape[1], shape[0], n, dtype.itemsize * 8,
                      None if interval is None else 1.0 / interval, None)


def tiff_frames(cam: CameraFile) -> Iterator[np.ndarray]:
    """The pages of a TIFF file, one decoded at a time."""
    import tifffile

    with tifffile.TiffFile(cam.path) as tif:
        for k, page in enumerate(tif.pages):
            img = page.asarray()
            if img.shape != (cam.height, cam.width):
                raise CameraFileError(f"{cam.path}: page {k} is {img.shape[1]}x{img.shape[0]} "
                                      f"px, the first {cam.width}x{cam.height}")
            yield img


OPENERS = {"mraw": open_mraw, "cine": open_cine, "tiff": open_tiff}
READERS = {"mraw": mraw_frames, "cine": cine_frames, "tiff": tiff_frames}
SUFFIXES = {"mraw": MRAW_SUFFIXES, "cine": CINE_SUFFIXES, "tiff": TIFF_SUFFIXES}


def open_camera_file(kind: str, path: str | Path) -> CameraFile:
    """`open_mraw`, `open_cine` or `open_tiff` by kind."""
    return OPENERS[kind](path)


def camera_frames(kind: str, cam: CameraFile) -> Iterator[np.ndarray]:
    """`mraw_frames`, `cine_frames` or `tiff_frames` by kind."""
    return READERS[kind](cam)
