"""GenICam cameras through harvesters and a GenTL producer (`.cti`), behind the camera port.

Any GenTL producer works (a camera vendor's, a frame grabber's). `bundled_producer()` finds
the emulating producer that the `genicam` wheel ships (`viky.cti`): 3 cameras (serials 0, 1, 2),
400x400 RGBa8 at 20 Hz, `PixelFormat` RGBa8 or Mono8, `AcquisitionFrameRate` 1-200 Hz in steps
of 1 Hz, `Width`/`Height` 100-800 px; no exposure, no offsets, no trigger, no time stamps.

Settings a device lacks are refused in one line (an exposure on a camera without
`ExposureTime`, a trigger without `TriggerMode`, a region offset without `OffsetX/OffsetY`),
never silently ignored.

Pixel formats: mono8 selects the camera's `Mono8`; mono16 its `Mono16`, else `Mono12`, else
`Mono10` (uint16 words, unscaled). `device_format="RGBa8"` (or RGB8, BGR8, BGRa8) makes the
camera send colour and the driver turn it into mono8 by the ITU-R BT.601 luma,
Y = 0.299 R + 0.587 G + 0.114 B, rounded (alpha ignored); `device_pixel_format` always names
what the camera sent. Frame counter: the GenTL buffer's frame id (64 bits). Camera clock: the
buffer's time stamp in ns when the producer gives one, else `device_time_s=None`.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
from genicam.gentl import TimeoutException
from harvesters.core import Harvester

from devices.camera.port import (MONO16_FORMATS, CameraLimits, CameraSettings, DriverBase, Frame,
                                 check_range, check_settings, pick_format, trigger_source)

_COLOUR = {"RGB8": (3, (0, 1, 2)), "RGBa8": (4, (0, 1, 2)),
           "BGR8": (3, (2, 1, 0)), "BGRa8": (4, (2, 1, 0))}   # channels, (R, G, B) indices
_LUMA = np.array([0.299, 0.587, 0.114])


def bundled_producer() -> Path | None:
    """The emulating GenTL producer shipped in the `genicam` wheel, or None."""
    try:
        import genicam
    except ImportError:
        return None
    found = sorted(Path(genicam.__file__).parent.rglob("*.cti"))
    return found[0] if found else None


def colour_to_mono8(data: np.ndarray, fmt: str, width: int, height: int) -> np.ndarray:
    """A colour buffer (RGB8, RGBa8, BGR8, BGRa8) as a mono8 image by the BT.601 luma."""
    channels, rgb = _COLOUR[fmt]
    pix = np.asarray(data, dtype=np.uint8).reshape(height, width, channels)[..., list(rgb)]
    return np.rint(pix @ _LUMA).astype(np.uint8)


class GenICamCamera(DriverBase):
    """One camera of a GenTL producer; see the module docstring.

    cti: path of the GenTL producer (`.cti`).
    serial: the camera's serial number; None picks the camera at `index`.
    device_format: a colour format for the camera to send (turned into mono8 here); None
        asks the camera for the port's format itself.
    """

    def __init__(self, cti: str | Path, serial: str | None = None, index: int = 0,
                 limits: CameraLimits | None = None, buffers: int = 64,
                 device_format: str | None = None):
        if device_format is not None and device_format not in _COLOUR:
            raise ValueError(f"device_format {device_format!r} is not one of "
                             f"{', '.join(_COLOUR)}")
        self.cti, self.serial, self.index = Path(cti), serial, index
        self.limits = limits if limits is not None else CameraLimits()
        self.buffers = buffers
        self.device_format = device_format
        self._h = None
        self._device = None
        self._info: dict[str, str] = {}
        self.settings: CameraSettings | None = None
        self.device_pixel_format: str | None = None
        self.counter_bits = (64, 0)

    # -- lifecycle -------------------------------------------------------------------------
    @property
    def identity(self) -> str:
        i = self._info
        if not i:
            return f"GenTL camera {self.serial or f'#{self.index}'} (not open)"
        return f"{i['vendor']} {i['model']} serial {i['serial']} ({i['id']})"

    def open(self) -> None:
        if self._device is not None:
            return
        if not self.cti.is_file():
            raise ValueError(f"GenTL producer {self.cti} does not exist")
        h = Harvester()
        try:
            h.add_file(str(self.cti))
            h.update()
            infos = list(h.device_info_list)
            seen = ", ".join(f"{d.serial_number} ({d.model})" for d in infos) or "none"
            if self.serial is not None:
                idx = [i for i, d in enumerate(infos) if str(d.serial_number) == str(self.serial)]
                if not idx:
                    raise ValueError(f"no GenTL camera with serial {self.serial} "
                                     f"from {self.cti.name}; visible: {seen}")
                index = idx[0]
            else:
                if not 0 <= self.index < len(infos):
                    raise ValueError(f"no GenTL camera at index {self.index} from "
                                     f"{self.cti.name}; visible: {seen}")
                index = self.index
            d = infos[index]
            self._device = h.create(index) if hasattr(h, "create") else \
                h.create_image_acquirer(list_index=index)
        except BaseException:
            h.reset()
            raise
        self._h = h
        self._info = {"vendor": str(d.vendor), "model": str(d.model),
                      "serial": str(d.serial_number), "id": str(d.id_)}

    # -- settings --------------------------------------------------------------------------
    def _has(self, name: str) -> bool:
        return self._device.remote_device.node_map.has_node(name)

    def _nm(self):
        return self._device.remote_device.node_map

    def configure(self, settings: CameraSettings) -> CameraSettings:
        check_settings(settings, self.limits)        # before the device is touched
        ia = self._require_open()
        if ia.is_acquiring():
            raise RuntimeError(f"{self.identity}: stop() before configure()")
        s = settings
        lacks = []
        if s.exposure_s is not None and not self._has("ExposureTime"):
            lacks.append("exposure time (ExposureTime)")
        if s.trigger != "free" and not self._has("TriggerMode"):
            lacks.append("trigger (TriggerMode)")
        if s.trigger == "software" and not self._has("TriggerSoftware"):
            lacks.append("software trigger (TriggerSoftware)")
        if s.roi is not None and (s.roi[0] or s.roi[1]) and not self._has("OffsetX"):
            lacks.append("region offset (OffsetX/OffsetY)")
        if not self._has("AcquisitionFrameRate"):
            lacks.append("frame rate (AcquisitionFrameRate)")
        if lacks:
            raise ValueError(f"{self.identity} has no {', no '.join(lacks)}")
        nm = self._nm()
        fmt = self._set_pixel_format(s.pixel_format)
        roi = self._set_roi(s.roi)
        if self._has("AcquisitionFrameRateEnable"):
            nm.AcquisitionFrameRateEnable.value = True
        rate = self._set_float("AcquisitionFrameRate", s.frame_rate_hz, "frame rate", "Hz")
        exposure = None
        if s.exposure_s is not None:
            if self._has("ExposureAuto"):
                nm.ExposureAuto.value = "Off"
            exposure = self._set_float("ExposureTime", s.exposure_s * 1e6, "exposure", "s",
                                       scale=1e6) * 1e-6
        elif self._has("ExposureTime"):
            exposure = float(nm.ExposureTime.value) * 1e-6
        self._set_trigger(s)
        self.device_pixel_format = fmt
        self.settings = CameraSettings(frame_rate_hz=rate, exposure_s=exposure, roi=roi,
                                       pixel_format=s.pixel_format, trigger=s.trigger,
                                       hardware_line=s.hardware_line)
        return self.settings

    def _set_float(self, name: str, value: float, what: str, unit: str,
                   scale: float = 1.0) -> float:
        node = getattr(self._nm(), name)
        check_range(value, node.min, node.max, what, unit, scale)
        node.value = type(node.value)(value) if isinstance(node.value, int) else float(value)
        return float(node.value)

    def _set_pixel_format(self, fmt: str) -> str:
        node = self._nm().PixelFormat
        if fmt == "mono8" and self.device_format is not None:
            wanted: tuple[str, ...] = (self.device_format,)
        else:
            wanted = ("Mono8",) if fmt == "mono8" else MONO16_FORMATS
        name = pick_format(wanted, tuple(node.symbolics), self.identity, fmt)
        node.value = name
        return name

    def _set_roi(self, roi) -> tuple[int, int, int, int]:
        nm = self._nm()
        has_offsets = self._has("OffsetX") and self._has("OffsetY")
        if has_offsets:
            nm.OffsetX.value = 0
            nm.OffsetY.value = 0
        if roi is None:
            roi = (0, 0, int(nm.Width.max), int(nm.Height.max))
        ox, oy, w, h = (int(v) for v in roi)
        for name, v in (("Width", w), ("Height", h)):
            node = getattr(nm, name)
            if not node.min <= v <= node.max:
                raise ValueError(f"roi {name.lower()} {v} px is outside the camera's range "
                                 f"{node.min}..{node.max} px")
            node.value = v - v % max(1, int(node.inc))
        if has_offsets:
            for name, v in (("OffsetX", ox), ("OffsetY", oy)):
                node = getattr(nm, name)
                if v > node.max:
                    raise ValueError(f"roi {tuple(roi)} reaches outside the camera's sensor")
                node.value = v - v % max(1, int(node.inc))
            ox, oy = int(nm.OffsetX.value), int(nm.OffsetY.value)
        return (ox, oy, int(nm.Width.value), int(nm.Height.value))

    def _set_trigger(self, s: CameraSettings) -> None:
        if not self._has("TriggerMode"):
            return                                    # free run only (checked above)
        nm = self._nm()
        if self._has("TriggerSelector"):
            nm.TriggerSelector.value = "FrameStart"
        if s.trigger == "free":
            nm.TriggerMode.value = "Off"
            return
        source = trigger_source(s, tuple(nm.TriggerSource.symbolics), self.identity)
        nm.TriggerMode.value = "On"
        nm.TriggerSource.value = source

    # -- acquisition -----------------------------------------------------------------------
    def start(self) -> None:
        ia = self._require_open()
        if self.settings is None:
            raise RuntimeError(f"{self.identity}: configure() before start()")
        ia.num_buffers = self.buffers
        ia.start()

    def trigger(self) -> None:
        ia = self._require_open()
        if self.settings is None or self.settings.trigger != "software":
            raise RuntimeError(f"{self.identity}: trigger() needs trigger='software'")
        if not ia.is_acquiring():
            raise RuntimeError(f"{self.identity}: start() before trigger()")
        self._nm().TriggerSoftware.execute()

    def grab(self, timeout_s: float) -> Frame | None:
        ia = self._require_open()
        try:
            with ia.fetch(timeout=max(1e-3, float(timeout_s))) as buf:
                host_ns = time.time_ns()
                c = buf.payload.components[0]
                fmt = str(c.data_format)
                if fmt in _COLOUR:
                    image = colour_to_mono8(c.data, fmt, c.width, c.height)
                else:
                    image = np.array(c.data, copy=True).reshape(c.height, c.width)
                counter = int(buf.frame_id)
                try:
                    ts_ns = int(buf.timestamp_ns)
                except Exception:                     # the producer keeps no time stamps
                    ts_ns = 0
        except TimeoutException:
            return None
        return Frame(image=image, counter=counter,
                     device_time_s=ts_ns * 1e-9 if ts_ns else None, host_time_ns=host_ns)

    def stop(self) -> None:
        if self._device is not None and self._device.is_acquiring():
            self._device.stop()

    def close(self) -> None:
        if self._device is None:
            return
        self.stop()
        self._device.destroy()
        self._device = None
        self._h.reset()
        self._h = None
