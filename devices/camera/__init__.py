"""Cameras: the port (`devices.camera.port`) and two drivers, `devices.camera.pylon` (Basler
pylon through pypylon) and `devices.camera.genicam` (any GenTL producer through harvesters).
The drivers import their vendor package when they are imported, so import them only where
a camera is used; the port needs numpy only."""

from devices.camera.port import (
    Camera,
    CameraLimits,
    CameraSettings,
    ClockMap,
    Frame,
    FrameCounter,
    check_settings,
)

__all__ = ["Camera", "CameraLimits", "CameraSettings", "ClockMap", "Frame", "FrameCounter",
           "check_settings"]
