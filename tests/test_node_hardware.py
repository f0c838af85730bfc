"""`ros_nodes.hardware`: the device behind the shaker and stage nodes' ports, from their
`hardware` parameter, without ROS: "sim" is the simulator with the node's own configuration
(as before lab files existed); "lab" with a simulated entry keeps the simulator's physics and
takes the lab file's limits; "lab" without a lab file is refused in one line. The camera node's
lab settings: the file's, with the node's overrides, checked against the file's limits."""

import dataclasses

import numpy as np
import pytest

from devices.lab import LabFileError
from hardware_sim.shaker import SimulatedShaker
from hardware_sim.stage import SimulatedStages
from ros_nodes import params as P
from devices.camera.port import CameraSettings
from ros_nodes.hardware import camera_settings, lab_camera, shaker_drive, stage_pair


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


def test_camera_settings_are_the_lab_files_with_the_node_overrides_within_the_limits(tmp_path):
    lab = tmp_path / "lab.toml"
    lab.write_text('[camera]\ndriver = "pylon"\nframe_rate_hz = 100.0\nexposure_s = 0.002\n'
                   'roi = [0, 0, 64, 32]\nmax_frame_rate_hz = 400.0\npixel_formats = ["mono8"]\n')
    cfg = P.from_flat(P.CameraNodeConfig, {"hardware": "lab", "lab_file": str(lab)})
    section = lab_camera(cfg)
    assert section.driver == "pylon"
    assert camera_settings(cfg, section) == CameraSettings(100.0, 0.002, (0, 0, 64, 32))
    over = dataclasses.replace(cfg, frame_rate_hz=200.0, exposure_s=0.001, trigger="software")
    assert camera_settings(over, section) == CameraSettings(200.0, 0.001, (0, 0, 64, 32),
                                                            trigger="software")
    for changes, why in (({"frame_rate_hz": 500.0}, "frame rate 500 Hz is above the limit 400 Hz"),
                         ({"frame_rate_hz": 1000.0, "exposure_s": 0.0}, "above the limit"),
                         ({"frame_rate_hz": 400.0, "exposure_s": 0.003},
                          "exposure 0.003 s is longer than the frame period 0.0025 s"),
                         ({"pixel_format": "mono16"}, "pixel format 'mono16' is not allowed")):
        with pytest.raises(ValueError, match=why):
            camera_settings(dataclasses.replace(cfg, **changes), section)


def test_the_camera_keeps_its_source_unless_the_lab_file_names_a_real_camera(tmp_path):
    lab = tmp_path / "lab.toml"
    lab.write_text("[stage]\nmax_strain = 0.03\n")          # no [camera]: the simulated one
    assert lab_camera(P.CameraNodeConfig()) is None
    assert lab_camera(P.from_flat(P.CameraNodeConfig, {"hardware": "lab",
                                                       "lab_file": str(lab)})) is None
    with pytest.raises(P.ConfigError, match="hardware 'lab' needs lab_file"):
        P.from_flat(P.CameraNodeConfig, {"hardware": "lab"})
