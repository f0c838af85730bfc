"""The camera port: what the rig asks of a camera, in SI units, and the logic every driver shares.

- `CameraSettings`: frame rate (Hz), exposure (s), region of interest (px), pixel format,
  trigger mode; `CameraLimits` and `check_settings`, which refuses settings outside the limits in
  one line before any driver call (the drivers call it first thing in `configure`).
- `Frame`: one image with the camera's own frame counter, the camera clock and the host clock.
- `Camera`: the protocol the drivers implement (`devices.camera.pylon`, `devices.camera.genicam`).
- `FrameCounter`: counts frames lost from jumps of the camera's counter (wrap-around included),
  so that frame loss is reported, never hidden.
- `ClockMap`: maps the camera clock to the host clock (and so to ROS time).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import Literal, Protocol, runtime_checkable

import numpy as np

PixelFormat = Literal["mono8", "mono16"]
Trigger = Literal["free", "software", "hardware"]
PIXEL_FORMATS: tuple[str, ...] = ("mono8", "mono16")
TRIGGERS: tuple[str, ...] = ("free", "software", "hardware")
Roi = tuple[int, int, int, int]  # offset_x, offset_y, width, height (px)


@dataclass(frozen=True)
class CameraSettings:
    """What the rig asks of a camera.

    frame_rate_hz: frames per second in free run; with a trigger, the highest rate the
        trigger will fire (the exposure must fit in its period).
    exposure_s: exposure time in seconds; None leaves the device's exposure as it is (a camera
        without an exposure setting accepts only None).
    roi: (offset_x, offset_y, width, height) in pixels, or None for the full sensor.
    pixel_format: "mono8" (uint8 frames) or "mono16" (uint16 frames).
    trigger: "free" (the camera's own rate), "software" (`Camera.trigger()`), or "hardware"
        (an edge on `hardware_line`).
    hardware_line: the camera input that triggers a frame when trigger is "hardware".
    """

    frame_rate_hz: float = 30.0
    exposure_s: float | None = None
    roi: Roi | None = None
    pixel_format: PixelFormat = "mono8"
    trigger: Trigger = "free"
    hardware_line: str = "Line1"


@dataclass(frozen=True)
class CameraLimits:
    """What a camera may be asked (from the lab file, or the device's own ranges).

    max_frame_rate_hz: the highest frame rate allowed.
    exposure_range_s: (shortest, longest) exposure allowed, seconds.
    pixel_formats: the pixel formats allowed.
    sensor_size_px: (width, height) of the full sensor, or None if unknown (then a region of
        interest is checked only for sign).
    """

    max_frame_rate_hz: float = 1.0e4
    exposure_range_s: tuple[float, float] = (1.0e-6, 10.0)
    pixel_formats: tuple[str, ...] = PIXEL_FORMATS
    sensor_size_px: tuple[int, int] | None = None


def check_settings(settings: CameraSettings, limits: CameraLimits) -> None:
    """Raise ValueError with a one-line reason if `settings` break `limits` or make no sense.

    Called by every driver before it touches the device. The exposure must fit in the frame
    period (1 / frame_rate_hz)."""
    s = settings
    if s.pixel_format not in PIXEL_FORMATS:
        raise ValueError(f"pixel format {s.pixel_format!r} is not one of {', '.join(PIXEL_FORMATS)}")
    if s.pixel_format not in limits.pixel_formats:
        raise ValueError(f"pixel format {s.pixel_format!r} is not allowed here "
                         f"(allowed: {', '.join(limits.pixel_formats)})")
    if s.trigger not in TRIGGERS:
        raise ValueError(f"trigger {s.trigger!r} is not one of {', '.join(TRIGGERS)}")
    if s.trigger == "hardware" and not (isinstance(s.hardware_line, str) and s.hardware_line):
        raise ValueError("a hardware trigger needs an input line (hardware_line, e.g. 'Line1')")
    rate = s.frame_rate_hz
    if not (isinstance(rate, (int, float)) and math.isfinite(rate) and rate > 0):
        raise ValueError(f"frame rate {rate!r} Hz must be a positive number")
    if rate > limits.max_frame_rate_hz:
        raise ValueError(f"frame rate {rate:g} Hz is above the limit "
                         f"{limits.max_frame_rate_hz:g} Hz")
    if s.exposure_s is not None:
        exp = s.exposure_s
        lo, hi = limits.exposure_range_s
        if not (isinstance(exp, (int, float)) and math.isfinite(exp) and exp > 0):
            raise ValueError(f"exposure {exp!r} s must be a positive number")
        if not lo <= exp <= hi:
            raise ValueError(f"exposure {exp:g} s is outside the allowed {lo:g}..{hi:g} s")
        if exp > 1.0 / rate:
            raise ValueError(f"exposure {exp:g} s is longer than the frame period "
                             f"{1.0 / rate:g} s at {rate:g} Hz")
    if s.roi is not None:
        roi = tuple(s.roi)
        if len(roi) != 4 or not all(isinstance(v, (int, np.integer)) for v in roi):
            raise ValueError(f"roi {s.roi!r} must be 4 integers (offset_x, offset_y, width, height)")
        ox, oy, w, h = roi
        if ox < 0 or oy < 0 or w <= 0 or h <= 0:
            raise ValueError(f"roi {s.roi!r} needs offsets >= 0 and a positive width and height")
        if limits.sensor_size_px is not None:
            sw, sh = limits.sensor_size_px
            if ox + w > sw or oy + h > sh:
                raise ValueError(f"roi {s.roi!r} reaches outside the {sw}x{sh} px sensor")


@dataclass
class Frame:
    """One image from a camera.

    image: 2-D numpy array, uint8 (mono8) or uint16 (mono16), rows x columns.
    counter: the camera's own frame counter (block id / frame id), as the device sent it.
    device_time_s: the camera clock at the frame, seconds; None when the device reports no
        clock (both vendor emulators send 0, which the drivers report as None).
    host_time_ns: the host clock (`time.time_ns()`) when the driver received the frame.
    """

    image: np.ndarray
    counter: int
    device_time_s: float | None
    host_time_ns: int


@runtime_checkable
class Camera(Protocol):
    """A camera as the rig uses it. Lifecycle: open -> configure -> start -> grab ... -> stop ->
    close; also a context manager (open on enter, stop and close on exit)."""

    @property
    def identity(self) -> str:
        """Vendor, model and serial number of the device, one line."""
        ...

    def open(self) -> None: ...

    def configure(self, settings: CameraSettings) -> CameraSettings:
        """Check `settings` against the limits (before the device is touched), apply them, and
        return what the device actually set (e.g. the frame rate rounded to its increment)."""
        ...

    def start(self) -> None: ...

    def trigger(self) -> None:
        """Fire one software trigger (settings.trigger must be "software")."""
        ...

    def grab(self, timeout_s: float) -> Frame | None:
        """The next frame, or None if none arrived within `timeout_s` seconds."""
        ...

    def stop(self) -> None: ...

    def close(self) -> None: ...

    def __enter__(self) -> Camera: ...

    def __exit__(self, *exc) -> None: ...


# what a driver shares, whatever the vendor API ------------------------------------------------
# mono16: the camera's 16-bit words, else its 12- or 10-bit ones (unscaled), in that order
MONO16_FORMATS = ("Mono16", "Mono12", "Mono10")


def pick_format(wanted: tuple[str, ...], offered: tuple[str, ...], identity: str,
                what: str) -> str:
    """The first of `wanted` the device offers; else a one-line refusal naming what it has."""
    for name in wanted:
        if name in offered:
            return name
    raise ValueError(f"{identity} offers no {'/'.join(wanted)} for {what} "
                     f"(pixel formats: {', '.join(offered)})")


def check_range(value: float, lo: float, hi: float, what: str, unit: str,
                scale: float = 1.0) -> None:
    """A one-line refusal if `value` is outside the device's own range [lo, hi] (all three in
    the device's units; shown divided by `scale`, in `unit`)."""
    if not lo <= value <= hi:
        raise ValueError(f"{what} {value / scale:g} {unit} is outside the camera's range "
                         f"{lo / scale:g}..{hi / scale:g} {unit}")


def trigger_source(settings: CameraSettings, offered: tuple[str, ...], identity: str) -> str:
    """The device's trigger source for `settings` ("Software" or the named input line), or a
    one-line refusal if the device does not offer it."""
    source = "Software" if settings.trigger == "software" else settings.hardware_line
    if source not in offered:
        raise ValueError(f"{identity} has no trigger source {source!r} "
                         f"(offered: {', '.join(offered)})")
    return source


class DriverBase:
    """The lifecycle every driver shares: a context manager (open on enter, stop and close on
    exit) and the refusal of a call that needs an open device. A driver keeps its device
    handle in `_device` (None while closed) and names itself in `identity`."""

    _device = None
    identity = "camera"

    def open(self) -> None:
        raise NotImplementedError

    def close(self) -> None:
        raise NotImplementedError

    def _require_open(self):
        if self._device is None:
            raise RuntimeError(f"{self.identity}: open() the camera first")
        return self._device

    def __enter__(self):
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class FrameCounter:
    """Counts frames lost from the camera's frame counter.

    Feed it every frame's counter in arrival order (`update`). A step of k > 1 means k - 1
    frames were lost; the counter wraps after `bits` bits to `wrap_to` (0 for a plain counter;
    GigE Vision's 16-bit block id skips 0 and wraps to 1). A step of 0 is a repeated frame,
    and a step backwards (more than half the counter range ahead, modulo the wrap) is counted
    as a restart of the camera's counter, not as loss.
    """

    def __init__(self, bits: int = 64, wrap_to: int = 0):
        if bits < 2 or wrap_to < 0 or wrap_to >= 2 ** bits - 1:
            raise ValueError(f"counter width {bits} bits with wrap to {wrap_to} makes no sense")
        self.bits, self.wrap_to = bits, wrap_to
        self._modulus = 2 ** bits - wrap_to
        self.last: int | None = None
        self.received = 0
        self.lost = 0
        self.repeated = 0
        self.restarts = 0

    def update(self, counter: int) -> int:
        """Record one frame's counter; return how many frames were lost just before it."""
        counter = int(counter)
        self.received += 1
        last, self.last = self.last, counter
        if last is None:
            return 0
        step = (counter - last) % self._modulus
        if step == 0:
            self.repeated += 1
            return 0
        if step > self._modulus // 2:
            self.restarts += 1
            return 0
        self.lost += step - 1
        return step - 1

    def summary(self) -> dict[str, int]:
        return {"received": self.received, "lost": self.lost, "repeated": self.repeated,
                "counter_restarts": self.restarts}


class ClockMap:
    """Maps the camera clock to the host clock: host_ns = device_s * 1e9 + offset_ns.

    Each frame gives a pair (device time, host time at retrieval). The host time is the device
    time plus the clock offset plus the transfer latency, which is never negative and varies
    from frame to frame. So the offset is estimated as the minimum of (host - device) over the
    last `window` pairs: the pair with the least latency bounds the offset best, and a late
    frame (a busy host) never pulls the estimate. The estimate is high by the smallest latency
    seen (for a camera on a link, some tens of microseconds to a few milliseconds); the window
    lets it follow a slow drift between the two clocks (crystal tolerances, ~1e-5).
    """

    def __init__(self, window: int = 1000):
        if window < 1:
            raise ValueError(f"clock map window {window} must be at least 1 pair")
        self.window = window
        self._n = 0
        self._mins: deque[tuple[int, int]] = deque()  # (index, diff_ns), diffs increasing

    def add(self, device_time_s: float, host_time_ns: int) -> None:
        diff = int(host_time_ns) - round(device_time_s * 1e9)
        while self._mins and self._mins[-1][1] >= diff:
            self._mins.pop()
        self._mins.append((self._n, diff))
        self._n += 1
        while self._mins[0][0] <= self._n - 1 - self.window:
            self._mins.popleft()

    @property
    def pairs(self) -> int:
        return self._n

    @property
    def offset_ns(self) -> int | None:
        """host minus device clock, ns (None before the first pair)."""
        return self._mins[0][1] if self._mins else None

    def to_host_ns(self, device_time_s: float) -> int:
        """The host time (ns since the epoch) of a device time."""
        if not self._mins:
            raise ValueError("the clock map has no (device, host) pair yet")
        return round(device_time_s * 1e9) + self._mins[0][1]
