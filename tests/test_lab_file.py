"""The lab file (`devices.lab`): the example read into the ports' own dataclasses, sections left
out are the simulated devices, and every mistake is one line naming the file, the section and
the key (unknown keys, wrong types, values outside a field's bounds, failed cross-checks)."""

import re

import pytest

from devices.camera.port import CameraSettings
from devices.lab import (EXAMPLE, SHAKER_EMULATOR_YAML, LabFileError, RosSection, read_lab,
                         ros_environment)
from devices.shaker.funcgen import FuncGenConfig
from devices.shaker.waveform import ShakerLimits
from devices.stage.port import StageLimits
from devices.stage.zaber import ZaberConfig


def _lab(tmp_path, text: str):
    path = tmp_path / "lab.toml"
    path.write_text(text)
    return read_lab(path)


def test_the_example_reads_into_the_ports_dataclasses():
    lab = read_lab(EXAMPLE)
    s = lab.shaker
    assert s.driver == "keysight33500b" and s.model == "33522B" and s.serial == ""
    assert s.address == "TCPIP0::emulated-33522b::inst0::INSTR"
    assert s.visa_library == f"{SHAKER_EMULATOR_YAML}@sim"      # "@sim": the package's model
    assert type(s.limits) is FuncGenConfig
    assert s.limits == FuncGenConfig(max_amplitude_m=0.010, m_per_v=0.002, max_volts=5.0)
    assert lab.stage.driver == "zaber" and lab.stage.port == "/dev/ttyUSB0"
    assert type(lab.stage.limits) is ZaberConfig and lab.stage.limits.closing_speed_m_s == 0.01
    assert lab.stage.limits.max_strain == 0.09 and lab.stage.device_id == 0
    c = lab.camera
    assert (c.driver, c.serial, c.cti) == ("pylon", "0815-0000", "")
    assert c.settings == CameraSettings(frame_rate_hz=100.0, exposure_s=0.002)
    assert c.limits.max_frame_rate_hz == 1000.0 and c.limits.exposure_range_s == (1e-5, 0.01)
    assert lab.ros == RosSection(0, "localhost", ())


def test_left_out_sections_are_the_simulated_devices_with_default_limits(tmp_path):
    lab = _lab(tmp_path, '[stage]\nmax_strain = 0.05\n')
    assert lab.shaker.driver == lab.camera.driver == "sim" and lab.stage.driver == "sim"
    assert lab.shaker.limits == ShakerLimits() and type(lab.stage.limits) is StageLimits
    assert lab.stage.limits.max_strain == 0.05
    assert lab.stage.limits.sample_height_m == StageLimits().sample_height_m
    assert ros_environment(lab.ros) == {"ROS_DOMAIN_ID": "0",
                                        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
    peers = _lab(tmp_path, '[ros]\ndomain_id = 42\ndiscovery = "subnet"\n'
                           'static_peers = ["rig-pc", "10.0.0.7"]\n').ros
    assert ros_environment(peers) == {"ROS_DOMAIN_ID": "42",
                                      "ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET",
                                      "ROS_STATIC_PEERS": "rig-pc;10.0.0.7"}


def test_relative_paths_are_relative_to_the_lab_file(tmp_path):
    (tmp_path / "gen.yaml").write_text(SHAKER_EMULATOR_YAML.read_text())
    lab = _lab(tmp_path, '[shaker]\ndriver = "keysight33500b"\naddress = "X"\n'
                         'visa_library = "gen.yaml@sim"\n'
                         '[camera]\ndriver = "genicam"\ncti = "producers/x.cti"\nserial = 1\n')
    assert lab.shaker.visa_library == f"{tmp_path / 'gen.yaml'}@sim"
    assert lab.camera.cti == str(tmp_path / "producers" / "x.cti")
    assert lab.camera.serial == "1"                     # serial = 1 and "1" alike


FG = '[shaker]\ndriver = "keysight33500b"\naddress = "TCPIP0::x::INSTR"\n'
MISTAKES = [
    # (file text, what the one line must say)
    ("[shaker]\nmax_amplitude = 0.01\n", r"\[shaker\] max_amplitude: unknown key \(known: driver"),
    (FG + "m_per_volt = 0.002\n", r"\[shaker\] m_per_volt: unknown key"),
    ("[shaker]\nm_per_v = 0.002\n",
     r"\[shaker\] m_per_v: only for driver 'keysight33500b' \(this section's driver is 'sim'\)"),
    ("[shaker]\nmax_amplitude_m = 0.2\n",
     r"\[shaker\] max_amplitude_m: 0.2 is above the maximum 0.05 \(largest accepted peak"),
    ("[shaker]\nmax_amplitude_m = \"10 mm\"\n",
     r"\[shaker\] max_amplitude_m: expected a number, got '10 mm'"),
    (FG + "max_volts = 0.0001\n", r"\[shaker\] max_volts: 0.0001 is below the minimum 0.001"),
    (FG + "max_points = 100.5\n", r"\[shaker\] max_points: expected an integer, got 100.5"),
    ("[shaker]\nmin_frequency_hz = 50.0\nmax_frequency_hz = 40.0\n",
     r"\[shaker\]: min_frequency_hz must be below max_frequency_hz"),
    ('[shaker]\ndriver = "keysight33500b"\n', r"\[shaker\] address: missing"),
    ('[shaker]\ndriver = "rigol"\n', r"\[shaker\] driver: 'rigol' is not one of sim, keysight"),
    (FG + 'visa_library = "nowhere.yaml@sim"\n',
     r"\[shaker\] visa_library: no pyvisa-sim device file .*nowhere.yaml"),
    ("[stage]\nmax_strain = \"5%\"\n", r"\[stage\] max_strain: expected a number, got '5%'"),
    ('[stage]\ndriver = "zaber"\nport = "/dev/ttyUSB0"\nbottom_device = true\n',
     r"\[stage\] bottom_device: expected an integer, got True"),
    ('[stage]\ndriver = "zaber"\nport = "/dev/ttyUSB0"\nclosing_speed_m_s = 0.2\n',
     r"\[stage\]: closing speed 0.2 m/s is a strain rate of 0.889/s, above the limit 0.25/s"),
    ('[stage]\ndriver = "zaber"\n', r"\[stage\] port: missing"),
    ('[stage]\nport = "/dev/ttyUSB0"\n', r"\[stage\] port: only for driver 'zaber'"),
    ("[stage]\nmin_strain = 0.05\nmax_strain = 0.02\n",
     r"\[stage\]: min_strain must not exceed max_strain"),
    ('[camera]\ndriver = "pylon"\nframe_rate_hz = 1000.0\nexposure_s = 0.002\n',
     r"\[camera\]: exposure 0.002 s is longer than the frame period 0.001 s"),
    ('[camera]\ndriver = "pylon"\nroi = [0, 0, 640]\n',
     r"\[camera\] roi: expected a list of 4 integers"),
    ('[camera]\ndriver = "pylon"\npixel_format = "rgb8"\n',
     r"\[camera\] pixel_format: 'rgb8' is not one of mono8, mono16"),
    ('[camera]\ndriver = "pylon"\nframe_rate_hz = 500.0\nmax_frame_rate_hz = 200.0\n',
     r"\[camera\]: frame rate 500 Hz is above the limit 200 Hz"),
    ('[camera]\ndriver = "pylon"\nserial = "a"\nindex = 1\n',
     r"\[camera\] index: give serial or index, not both"),
    ('[camera]\ndriver = "genicam"\n', r"\[camera\] cti: missing"),
    ('[camera]\ndriver = "pylon"\ncti = "x.cti"\n', r"\[camera\] cti: only for driver 'genicam'"),
    ("[camera]\nframe_rate_hz = 100.0\n",
     r"\[camera\] frame_rate_hz: only for driver 'pylon' or 'genicam'"),
    ("[ros]\ndomain_id = 300\n", r"\[ros\] domain_id: must be in 0..232, got 300"),
    ('[ros]\ndiscovery = "everywhere"\n',
     r"\[ros\] discovery: 'everywhere' is not one of localhost, subnet, off"),
    ("[ros]\nstatic_peers = \"rig-pc\"\n", r"\[ros\] static_peers: expected a list of host"),
    ("[laser]\npower_w = 1.0\n", r"lab.toml: laser: unknown section \(known: shaker, stage"),
    ('format = "metarig-lab/2"\n', r"lab.toml: format: expected 'metarig-lab/1'"),
    ("shaker = 3\n", r"lab.toml: shaker: must be a section"),
    ("[shaker\nmax_amplitude_m = 0.01\n", r"lab.toml: not valid TOML: .*line 1"),
]


@pytest.mark.parametrize("text, says", MISTAKES, ids=[m[1][:40] for m in MISTAKES])
def test_every_mistake_is_one_line_naming_file_section_and_key(tmp_path, text, says):
    with pytest.raises(LabFileError) as e:
        _lab(tmp_path, text)
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith(str(tmp_path / "lab.toml"))
    assert e.value.__cause__ is None or e.value.__suppress_context__
    assert re.search(says, msg), msg


def test_a_missing_file_is_one_line(tmp_path):
    with pytest.raises(LabFileError, match=r"nope.toml: no such lab file$"):
        read_lab(tmp_path / "nope.toml")
    with pytest.raises(LabFileError, match=r"is a folder, not a lab file$"):
        read_lab(tmp_path)
