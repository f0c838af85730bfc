"""The device behind the shaker and stage nodes' ports, from their `hardware` parameter.

- "sim": the simulated device with the node's `device.*` parameters (as always).
- "lab": the [shaker] / [stage] section of the node's `lab_file` (`devices.lab`): a real
  driver opened and checked by `devices.connect`, or, for `driver = "sim"`, the simulated
  device with the lab file's limits in place of the node's `device.*` limits (its physics
  stay the node's).
Pure (no rclpy): the nodes call these in their configure transition. A lab file that cannot be
used raises `LabFileError`, a device that cannot be opened `DeviceError` (one line each).
"""

import dataclasses

import numpy as np

from devices.lab import read_lab
from devices.shaker.port import ShakerDrive
from devices.shaker.waveform import ShakerLimits
from devices.stage.port import StageLimits, StagePair
from ros_nodes.params import ShakerNodeConfig, StageNodeConfig


def with_limits(device, limits, limits_cls):
    """`device` (a simulator config that extends `limits_cls`) with the fields of `limits_cls`
    taken from `limits`."""
    return dataclasses.replace(device, **{f.name: getattr(limits, f.name)
                                          for f in dataclasses.fields(limits_cls)})


def shaker_drive(cfg: ShakerNodeConfig, rng: np.random.Generator) -> ShakerDrive:
    """The shaker the node's parameters name (see the module docstring)."""
    device = cfg.device
    if cfg.hardware == "lab":
        section = read_lab(cfg.lab_file).shaker
        if section.driver != "sim":
            from devices.connect import open_shaker

            return open_shaker(section)
        device = with_limits(device, section.limits, ShakerLimits)
    from hardware_sim.shaker import SimulatedShaker

    return SimulatedShaker(device, rng)


def stage_pair(cfg: StageNodeConfig, rng: np.random.Generator) -> StagePair:
    """The stages the node's parameters name (see the module docstring)."""
    device = cfg.device
    if cfg.hardware == "lab":
        section = read_lab(cfg.lab_file).stage
        if section.driver != "sim":
            from devices.connect import open_stages

            return open_stages(section)
        device = with_limits(device, section.limits, StageLimits)
    from hardware_sim.stage import SimulatedStages

    return SimulatedStages(device, rng)
