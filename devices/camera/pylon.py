"""Basler pylon cameras through pypylon, behind the camera port (`devices.camera.port`).

`PylonCamera(serial=...)` or `PylonCamera(index=...)` picks one of the cameras pylon sees
(`list_cameras()`). pylon's camera emulator stands in for a camera: `PYLON_CAMEMU=N` in the
environment before pylon's transport-layer factory is first used gives N emulated cameras
(serials 0815-0000, 0815-0001, ...; Mono8 1024x1040 at start, up to 4096x4096).

Node names (SFNC, as Basler's USB3 and newer GigE cameras and the emulator use them):
`AcquisitionFrameRateEnable`/`AcquisitionFrameRate` (Hz), `ExposureTime` (microseconds),
`Width/Height/OffsetX/OffsetY`, `PixelFormat`, `TriggerSelector=FrameStart`, `TriggerMode`,
`TriggerSource` (`Software` or an input line), `TriggerSoftware`. Older GigE cameras name the
rate and exposure `AcquisitionFrameRateAbs` and `ExposureTimeAbs`; both are tried.

Frame counter: the grab result's block id. Camera clock: the grab result's time stamp in
ticks, divided by `GevTimestampTickFrequency` or `TimestampTickFrequency` when the camera has
one, else by 1 GHz (USB3 Vision and SFNC 2 cameras count nanoseconds). The emulator sends
time stamp 0, reported as `device_time_s=None`.

mono16 selects `Mono16`, else `Mono12`, else `Mono10` (what the camera offers, in that order);
the frame is the camera's uint16 words unscaled, and `device_pixel_format` says which it was.

Emulated images: `emulator_images=PATH` (emulator only) switches the test pattern off and the
emulator's image-file mode on: a folder is played in a loop, one file per frame in name order,
a single file is repeated (PNG and TIFF read; the image must match the region of interest).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
from pypylon import genicam as _gc
from pypylon import pylon

from devices.camera.port import (MONO16_FORMATS, CameraLimits, CameraSettings, DriverBase, Frame,
                                 check_range, check_settings, pick_format, trigger_source)

EMULATOR_CLASS = "BaslerCamEmu"
_DEFAULT_TICK_HZ = 1.0e9


def list_cameras() -> list[dict[str, str]]:
    """The cameras pylon sees: serial, model, vendor, device class (one dict each)."""
    devs = pylon.TlFactory.GetInstance().EnumerateDevices()
    return [{"serial": d.GetSerialNumber(), "model": d.GetModelName(),
             "vendor": d.GetVendorName(), "device_class": d.GetDeviceClass()} for d in devs]


def _readable(cam, name: str) -> bool:
    return _gc.IsReadable(cam.GetNodeMap().GetNode(name))


class PylonCamera(DriverBase):
    """One Basler camera (or emulated camera) through pypylon; see the module docstring.

    serial: the camera's serial number; None picks the camera at `index` of `list_cameras()`.
    limits: what may be asked of it (checked before the device is touched).
    buffers: frames pylon may hold for the host (MaxNumBuffer) before it drops.
    emulator_images: a folder or image file the emulator plays instead of its test pattern.
    """

    def __init__(self, serial: str | None = None, index: int = 0,
                 limits: CameraLimits | None = None, buffers: int = 64,
                 emulator_images: str | Path | None = None):
        self.serial, self.index = serial, index
        self.limits = limits if limits is not None else CameraLimits()
        self.buffers = buffers
        self.emulator_images = emulator_images
        self._device = None
        self._info: dict[str, str] = {}
        self._tick_hz = _DEFAULT_TICK_HZ
        self.settings: CameraSettings | None = None
        self.device_pixel_format: str | None = None
        self.failed_grabs = 0
        self.last_error = ""

    # -- lifecycle -------------------------------------------------------------------------
    @property
    def identity(self) -> str:
        i = self._info
        if not i:
            return f"pylon camera {self.serial or f'#{self.index}'} (not open)"
        return f"{i['vendor']} {i['model']} serial {i['serial']} ({i['device_class']})"

    @property
    def is_emulator(self) -> bool:
        return self._info.get("device_class") == EMULATOR_CLASS

    @property
    def counter_bits(self) -> tuple[int, int]:
        """(bits, wrap_to) of the block id, for `FrameCounter(*cam.counter_bits)`: GigE Vision's
        16-bit block id wraps to 1; USB3 and the emulator count with 64 bits from 0."""
        return (16, 1) if self._info.get("device_class") == "BaslerGigE" else (64, 0)

    def open(self) -> None:
        if self._device is not None:
            return
        factory = pylon.TlFactory.GetInstance()
        devs = list(factory.EnumerateDevices())
        seen = ", ".join(f"{d.GetSerialNumber()} ({d.GetModelName()})" for d in devs) or "none"
        if self.serial is not None:
            match = [d for d in devs if d.GetSerialNumber() == str(self.serial)]
            if not match:
                raise ValueError(f"no pylon camera with serial {self.serial}; visible: {seen}")
            dev = match[0]
        else:
            if not 0 <= self.index < len(devs):
                raise ValueError(f"no pylon camera at index {self.index}; visible: {seen}")
            dev = devs[self.index]
        cam = pylon.InstantCamera(factory.CreateDevice(dev))
        cam.Open()
        self._device = cam
        self._info = {"serial": dev.GetSerialNumber(), "model": dev.GetModelName(),
                      "vendor": dev.GetVendorName(), "device_class": dev.GetDeviceClass()}
        self._tick_hz = _DEFAULT_TICK_HZ
        for name in ("GevTimestampTickFrequency", "TimestampTickFrequency"):
            if _readable(cam, name):
                self._tick_hz = float(cam.GetNodeMap().GetNode(name).GetValue())
                break
        if self.emulator_images is not None:
            self._play_images(Path(self.emulator_images))

    def _play_images(self, path: Path) -> None:
        if not self.is_emulator:
            raise ValueError(f"emulator_images works on pylon's emulator only, not {self.identity}")
        if not path.exists():
            raise ValueError(f"emulator_images {path} does not exist")
        cam = self._device
        cam.TestImageSelector.Value = "Off"   # the test pattern overrides the image files
        cam.ImageFilename.Value = str(path)
        cam.ImageFileMode.Value = "On"

    # -- settings --------------------------------------------------------------------------
    def configure(self, settings: CameraSettings) -> CameraSettings:
        check_settings(settings, self.limits)        # before the device is touched
        cam = self._require_open()
        if cam.IsGrabbing():
            raise RuntimeError(f"{self.identity}: stop() before configure()")
        self._check_device_supports(settings)
        fmt = self._set_pixel_format(settings.pixel_format)
        roi = self._set_roi(settings.roi)
        rate = self._set_frame_rate(settings.frame_rate_hz)
        exposure = self._set_exposure(settings.exposure_s)
        self._set_trigger(settings)
        self.device_pixel_format = fmt
        self.settings = CameraSettings(frame_rate_hz=rate, exposure_s=exposure, roi=roi,
                                       pixel_format=settings.pixel_format,
                                       trigger=settings.trigger,
                                       hardware_line=settings.hardware_line)
        return self.settings

    def _node(self, *names: str):
        nm = self._device.GetNodeMap()
        for name in names:
            if _gc.IsWritable(nm.GetNode(name)):
                return nm.GetNode(name)
        return None

    def _check_device_supports(self, s: CameraSettings) -> None:
        lacks = []
        if s.exposure_s is not None and self._node("ExposureTime", "ExposureTimeAbs") is None:
            lacks.append("an exposure time (ExposureTime)")
        if self._node("AcquisitionFrameRate", "AcquisitionFrameRateAbs") is None:
            lacks.append("a frame rate (AcquisitionFrameRate)")
        if s.trigger != "free" and self._node("TriggerMode") is None:
            lacks.append("a trigger (TriggerMode)")
        if lacks:
            raise ValueError(f"{self.identity} has no {' and no '.join(lacks)}")

    def _set_pixel_format(self, fmt: str) -> str:
        node = self._node("PixelFormat")
        name = pick_format(("Mono8",) if fmt == "mono8" else MONO16_FORMATS,
                           tuple(node.GetSymbolics()), self.identity, fmt)
        node.SetValue(name)
        return name

    def _set_roi(self, roi) -> tuple[int, int, int, int]:
        cam = self._device
        wmax, hmax = int(cam.WidthMax.GetValue()), int(cam.HeightMax.GetValue())
        if roi is None:
            roi = (0, 0, wmax, hmax)
        ox, oy, w, h = (int(v) for v in roi)
        if ox + w > wmax or oy + h > hmax:
            raise ValueError(f"roi {tuple(roi)} reaches outside the camera's {wmax}x{hmax} px")
        cam.OffsetX.SetValue(0)
        cam.OffsetY.SetValue(0)
        for node, v in ((cam.Width, w), (cam.Height, h), (cam.OffsetX, ox), (cam.OffsetY, oy)):
            inc = max(1, int(node.GetInc()))
            node.SetValue(max(int(node.GetMin()), v - v % inc))   # down to the increment
        return (int(cam.OffsetX.GetValue()), int(cam.OffsetY.GetValue()),
                int(cam.Width.GetValue()), int(cam.Height.GetValue()))

    def _set_frame_rate(self, rate_hz: float) -> float:
        enable = self._node("AcquisitionFrameRateEnable")
        if enable is not None:
            enable.SetValue(True)
        node = self._node("AcquisitionFrameRate", "AcquisitionFrameRateAbs")
        check_range(rate_hz, node.GetMin(), node.GetMax(), "frame rate", "Hz")
        node.SetValue(float(rate_hz))
        return float(node.GetValue())

    def _set_exposure(self, exposure_s: float | None) -> float | None:
        node = self._node("ExposureTime", "ExposureTimeAbs")
        if exposure_s is not None:
            auto = self._node("ExposureAuto")
            if auto is not None:
                auto.SetValue("Off")
            check_range(exposure_s * 1e6, node.GetMin(), node.GetMax(), "exposure", "s",
                        scale=1e6)
            node.SetValue(exposure_s * 1e6)
        return None if node is None else float(node.GetValue()) * 1e-6

    def _set_trigger(self, s: CameraSettings) -> None:
        cam = self._device
        if self._node("TriggerSelector") is not None:
            cam.TriggerSelector.SetValue("FrameStart")
        if s.trigger == "free":
            if self._node("TriggerMode") is not None:
                cam.TriggerMode.SetValue("Off")
            return
        source = trigger_source(s, tuple(cam.TriggerSource.GetSymbolics()), self.identity)
        cam.TriggerMode.SetValue("On")
        cam.TriggerSource.SetValue(source)

    # -- acquisition -----------------------------------------------------------------------
    def start(self) -> None:
        cam = self._require_open()
        if self.settings is None:
            raise RuntimeError(f"{self.identity}: configure() before start()")
        cam.MaxNumBuffer.SetValue(self.buffers)
        cam.StartGrabbing(pylon.GrabStrategy_OneByOne)

    def trigger(self) -> None:
        cam = self._require_open()
        if self.settings is None or self.settings.trigger != "software":
            raise RuntimeError(f"{self.identity}: trigger() needs trigger='software'")
        if not cam.IsGrabbing():
            raise RuntimeError(f"{self.identity}: start() before trigger()")
        if not cam.WaitForFrameTriggerReady(1000, pylon.TimeoutHandling_Return):
            raise RuntimeError(f"{self.identity} was not ready for a trigger within 1 s")
        cam.TriggerSoftware.Execute()

    def grab(self, timeout_s: float) -> Frame | None:
        """The next frame, or None on a timeout or a failed grab (a failed grab is counted in
        `failed_grabs`, its reason kept in `last_error`; the frame counter shows the gap)."""
        cam = self._require_open()
        result = cam.RetrieveResult(max(0, int(round(timeout_s * 1000))),
                                    pylon.TimeoutHandling_Return)
        host_ns = time.time_ns()
        if result is None or not result.IsValid():
            return None
        try:
            if not result.GrabSucceeded():
                self.failed_grabs += 1
                self.last_error = result.GetErrorDescription()
                return None
            image = np.array(result.GetArray(), copy=True)
            ticks = int(result.TimeStamp)
            return Frame(image=image, counter=int(result.BlockID),
                         device_time_s=ticks / self._tick_hz if ticks else None,
                         host_time_ns=host_ns)
        finally:
            result.Release()

    def stop(self) -> None:
        if self._device is not None and self._device.IsGrabbing():
            self._device.StopGrabbing()

    def close(self) -> None:
        if self._device is None:
            return
        self.stop()
        self._device.Close()
        self._device.DestroyDevice()
        self._device = None
