"""`ros_nodes.hardware`: the device behind the shaker and stage nodes' ports, from their
`hardware` parameter, without ROS: "sim" is the simulator with the node's own configuration
(as before lab files existed); "lab" with a simulated entry keeps the simulator's physics and
takes the lab file's limits; "lab" without a lab file is refused in one line."""

import dataclasses

import numpy as np
import pytest

from devices.lab import LabFileError
from hardware_sim.shaker import SimulatedShaker
from hardware_sim.stage import SimulatedStages
from ros_nodes import params as P
from ros_nodes.hardware import shaker_drive, stage_pair


def test_sim_is_the_simulator_with_the_node_configuration():
    cfg = P.from_flat(P.ShakerNodeConfig, {"device.max_amplitude_m": 0.008})
    drive = shaker_drive(cfg, np.random.default_rng(0))
    assert type(drive) is SimulatedShaker and drive.limits == cfg.device
    stages = stage_pair(P.StageNodeConfig(), np.random.default_rng(0))
    assert type(stages) is SimulatedStages and stages.limits == P.StageNodeConfig().device


def test_a_simulated_lab_entry_takes_the_lab_limits_and_keeps_the_physics(tmp_path):
    lab = tmp_path / "lab.toml"
    lab.write_text("[shaker]\nmax_amplitude_m = 0.005\nmax_frequency_hz = 80.0\n"
                   "[stage]\nmax_strain = 0.03\nsample_height_m = 0.3\n")
    cfg = P.from_flat(P.ShakerNodeConfig, {"hardware": "lab", "lab_file": str(lab),
                                           "device.max_amplitude_m": 0.008})
    drive = shaker_drive(cfg, np.random.default_rng(0))
    assert type(drive) is SimulatedShaker
    assert drive.limits.max_amplitude_m == 0.005 and drive.limits.max_frequency_hz == 80.0
    assert drive.limits == dataclasses.replace(cfg.device, max_amplitude_m=0.005,
                                               max_frequency_hz=80.0)
    scfg = P.from_flat(P.StageNodeConfig, {"hardware": "lab", "lab_file": str(lab)})
    stages = stage_pair(scfg, np.random.default_rng(0))
    assert stages.limits == dataclasses.replace(scfg.device, max_strain=0.03,
                                                sample_height_m=0.3)


def test_lab_needs_a_usable_lab_file(tmp_path):
    with pytest.raises(P.ConfigError, match="hardware 'lab' needs lab_file"):
        P.from_flat(P.StageNodeConfig, {"hardware": "lab"})
    cfg = P.from_flat(P.ShakerNodeConfig, {"hardware": "lab",
                                           "lab_file": str(tmp_path / "none.toml")})
    with pytest.raises(LabFileError, match="none.toml: no such lab file"):
        shaker_drive(cfg, np.random.default_rng(0))
