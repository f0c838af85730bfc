"""Helpers for the tests of `metarig rig --hardware lab` on the emulators: the lab file (the
pyvisa-sim 33522B, the Zaber emulator's port, pylon's emulated camera, the test's domain), the
run's flags, the MCAP read back with the `mcap` package, and reading a run's output up to a
line."""

import os
import subprocess
import sys
import time
from pathlib import Path

BIN = sys.prefix + "/bin/"
DOMAIN = os.environ["ROS_DOMAIN_ID"]
HEIGHT_M, MICROSTEP_M = 0.06, 1e-6
CAMERA = """[camera]
driver = "pylon"
serial = "0815-0000"
frame_rate_hz = 100.0
exposure_s = 0.002
roi = [0, 0, 320, 240]
max_frame_rate_hz = 500.0
exposure_range_s = [1e-5, 0.01]
"""


def lab_text(port: str, domain: str = DOMAIN) -> str:
    return f"""format = "metarig-lab/1"
[shaker]
driver = "keysight33500b"
address = "TCPIP0::emulated-33522b::inst0::INSTR"
visa_library = "@sim"
model = "33522B"
m_per_v = 0.002
max_volts = 5.0
max_amplitude_m = 0.010
[stage]
driver = "zaber"
port = "{port}"
sample_height_m = {HEIGHT_M}
max_strain = 0.05
microstep_m = {MICROSTEP_M}
closing_speed_m_s = 0.01
reply_timeout_s = 2.0          # the emulator's thread shares this busy 2-core machine
eta_margin_s = 2.0
bottom_device = 1
top_device = 2
{CAMERA}[ros]
domain_id = {domain}
discovery = "localhost"
"""


RUN = ["--nx", "6", "--ny", "5", "--strain", "0.02", "--amplitude", "0.005", "--settle-s",
       "0.05"]


def read_mcap(path: Path) -> tuple[str, dict[str, list]]:
    """(profile, topic -> [(log_time ns, decoded message)]) through the mcap package."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    out: dict[str, list] = {}
    with path.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        profile = reader.get_header().profile
        for _, channel, message, decoded in reader.iter_decoded_messages():
            out.setdefault(channel.topic, []).append((message.log_time, decoded))
    return profile, out


def start_lab_rig(start_node, tmp_path: Path, port: str, env: dict, *args: str):
    """`metarig rig --hardware lab` (the `start_node` fixture) on the emulators' lab file with
    the stage controller on `port`, `RUN` and `args`: (process, lab file, run folder)."""
    lab, out = tmp_path / "lab.toml", tmp_path / "run"
    lab.write_text(lab_text(port))
    proc = start_node([BIN + "metarig", "rig", "--hardware", "lab", "--lab", lab, "--out", out,
                       *RUN, *args], env=env)
    return proc, lab, out


def read_until(proc: subprocess.Popen, text: str, timeout_s: float) -> list[str]:
    """The output lines of `proc` up to the first holding `text` (AssertionError if none comes
    within `timeout_s`)."""
    lines, deadline = [], time.monotonic() + timeout_s
    for line in proc.stdout:
        lines.append(line)
        if text in line or time.monotonic() > deadline:
            break
    assert any(text in x for x in lines), "".join(lines)
    return lines
