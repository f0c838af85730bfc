"""The device behind the shaker, stage and camera nodes' ports, from their `hardware` parameter.

- "sim": the simulated device with the node's `device.*` parameters (as always).
- "lab": the [shaker] / [stage] section of the node's `lab_file` (`devices.lab`): a real
  driver opened and checked by `devices.connect`, or, for `driver = "sim"`, the simulated
  device with the lab file's limits in place of the node's `device.*` limits (its physics
  stay the node's).
- the camera: "sim" keeps the frames of the node's `source` (simulated or replayed), and so
  does "lab" with `driver = "sim"`; "lab" with a real driver opens the camera of the file's
  [camera] (`lab_camera`, `camera_device`), with the settings of the file and the node's
  overrides, checked against the file's limits before the device is configured
  (`camera_settings`).
Pure (no rclpy): the nodes call these in their configure transition (the camera node when it
starts). A lab file that cannot be used raises `LabFileError`, a device that cannot be opened
`DeviceError` (a camera driver `ValueError`), one line each.
"""

import dataclasses
import importlib

import numpy as np

from devices.camera.port import Camera, CameraSettings, check_settings
from devices.lab import CameraSection, read_lab
from devices.shaker.port import ShakerDrive
from devices.shaker.waveform import ShakerLimits
from devices.stage.port import StageLimits, StagePair
from ros_nodes.params import CameraNodeConfig, ShakerNodeConfig, StageNodeConfig


def with_limits(device, limits, limits_cls):
    """`device` (a simulator config that extends `limits_cls`) with the fields of `limits_cls`
    taken from `limits`."""
    return dataclasses.replace(device, **{f.name: getattr(limits, f.name)
                                          for f in dataclasses.fields(limits_cls)})


def _device(cfg, kind: str, limits_cls, rng: np.random.Generator):
    """The `kind` ("shaker" or "stage") device the node's parameters name: a real driver opened
    by `devices.connect` for a lab section with one, else the simulator (imported only then)
    with the lab section's limits (hardware "lab") or the node's `device.*` ones."""
    device = cfg.device
    if cfg.hardware == "lab":
        section = getattr(read_lab(cfg.lab_file), kind)
        if section.driver != "sim":
            from devices import connect

            return getattr(connect, DRIVERS[kind][0])(section)
        device = with_limits(device, section.limits, limits_cls)
    module, name = DRIVERS[kind][1].split(":")
    return getattr(importlib.import_module(module), name)(device, rng)


# per lab section: the opener in devices.connect and the simulator
DRIVERS = {"shaker": ("open_shaker", "hardware_sim.shaker:SimulatedShaker"),
           "stage": ("open_stages", "hardware_sim.stage:SimulatedStages")}


def shaker_drive(cfg: ShakerNodeConfig, rng: np.random.Generator) -> ShakerDrive:
    """The shaker the node's parameters name (see the module docstring)."""
    return _device(cfg, "shaker", ShakerLimits, rng)


def stage_pair(cfg: StageNodeConfig, rng: np.random.Generator) -> StagePair:
    """The stages the node's parameters name (see the module docstring)."""
    return _device(cfg, "stage", StageLimits, rng)


def lab_camera(cfg: CameraNodeConfig) -> CameraSection | None:
    """The [camera] section of the node's lab file when it names a real camera ("pylon" or
    "genicam"); None when the node keeps its `source` (hardware "sim", or a "sim" entry)."""
    if cfg.hardware != "lab":
        return None
    section = read_lab(cfg.lab_file).camera
    return None if section.driver == "sim" else section


def camera_settings(cfg: CameraNodeConfig, section: CameraSection) -> CameraSettings:
    """What the node asks of the lab camera: the lab file's settings with the node's overrides
    (`frame_rate_hz`, `exposure_s`, `pixel_format`, `trigger`; 0 or empty keeps the file's),
    checked against the file's limits before any device is configured (ValueError, one line)."""
    over = {}
    if cfg.frame_rate_hz > 0:
        over["frame_rate_hz"] = cfg.frame_rate_hz
    if cfg.exposure_s > 0:
        over["exposure_s"] = cfg.exposure_s
    if cfg.pixel_format:
        over["pixel_format"] = cfg.pixel_format
    if cfg.trigger:
        over["trigger"] = cfg.trigger
    settings = dataclasses.replace(section.settings, **over)
    check_settings(settings, section.limits)
    return settings


def camera_device(section: CameraSection) -> Camera:
    """The camera of a real [camera] section, open and its identity checked (not configured)."""
    from devices.connect import open_camera

    return open_camera(section)
