"""`metarig rig --hardware lab` when a device stops answering during the capture: the emulated
Zaber stages fall silent (a pulled cable) after the pulse; the stage node puts them in FAULT,
the run ends at once with one line and exit 1, every device is told to stop, and the
recording keeps everything up to that moment (read back with the `mcap` package)."""

import json
import sys
import time

import pytest

pytest.importorskip("pypylon", reason="pip install pypylon")
pytest.importorskip("pyvisa_sim", reason="pip install pyvisa-sim")

from labrig import read_mcap, read_until, start_lab_rig  # noqa: E402

from ros_nodes import topics as T  # noqa: E402


def test_stages_that_stop_answering_end_the_run_with_one_line(tmp_path, emu, lab_env,
                                                             start_node):
    proc, _, out = start_lab_rig(start_node, tmp_path, emu.port, lab_env, "--record-s", "60")
    lines = read_until(proc, "phase pulse", 90.0)
    time.sleep(0.5)
    emu.silent = True  # the controller reads and never answers
    t0 = time.monotonic()
    rest, _ = proc.communicate(timeout=120)
    text = "".join(lines) + rest
    assert proc.returncode == 1, text[-3000:]
    # not the 60 s capture: ended by the fault (the margin takes a loaded machine's stalls of
    # several seconds, one of 8 s on record)
    assert time.monotonic() - t0 < 40
    assert "Traceback" not in text
    why = "stage fault: no reply from the stage controller on " + emu.port
    errors = [x for x in text.splitlines() if "metarig.rig:" in x and why in x]
    assert errors and "\n" not in errors[0]
    run = json.loads((out / "run.json").read_text())
    assert run["status"].startswith("failed: " + why)
    assert [p["phase"] for p in run["phases"]][-2:] == ["stop", "aborted"]
    assert "[shaker]: stop (rig stop)" in text and "the camera stops streaming" in text
    _, msgs = read_mcap(out / "recording.mcap")  # complete, with what came before the fault
    assert len(msgs[T.IMAGE.name]) == run["recording"]["topics"][T.IMAGE.name]["count"] > 20
    assert any(m.data.startswith("fault") for _, m in msgs[T.STAGE_STATE.name])
    assert msgs[T.RIG_STOP.name] and msgs[T.SHAKER_COMMAND.name]


# `metarig rig` in a process of its own whose function-generator drive is reachable: once the
# pulse has been triggered, the emulated 33522B queues an error (the instrument's own, as a
# real one reports an overload) or stops answering (a pulled LAN cable: every VISA call times
# out); the driver's watchdog finds either
GENERATOR_FAULT_MID_RUN = """
import os, sys, threading, time
from pyvisa.constants import StatusCode
from pyvisa.errors import VisaIOError
from devices import connect
from ros_nodes.cli_rig import rig_main

opened = []
real = connect.open_shaker
connect.open_shaker = lambda *a, **kw: opened.append(real(*a, **kw)) or opened[-1]

def inject():
    while not (opened and opened[-1].started_s is not None):
        time.sleep(0.01)
    drive = opened[-1]
    with drive._io:
        if os.environ["FAULT"] == "error":
            drive._device.write("SOUR:BOGUS 1")
        else:
            def timeout(*a, **kw):
                raise VisaIOError(StatusCode.error_timeout)
            drive._device.write = timeout
    print("injected: " + os.environ["FAULT"], flush=True)

threading.Thread(target=inject, daemon=True).start()
sys.exit(rig_main(sys.argv[1:]))
"""


@pytest.mark.parametrize("fault, why", [
    ("error", 'reports -100,"Command error"; output turned off'),
    ("silent", "did not answer 'SYST:ERR?': VI_ERROR_TMO"),
])
def test_a_generator_fault_mid_run_stops_its_output_and_ends_the_run_in_one_line(
        tmp_path, emu, lab_env, start_node, fault, why):
    from labrig import RUN, lab_text

    lab, out = tmp_path / "lab.toml", tmp_path / "run"
    lab.write_text(lab_text(emu.port).replace("max_volts = 5.0", "max_volts = 5.0\n"
                                              "watchdog_s = 0.1"))
    proc = start_node([sys.executable, "-c", GENERATOR_FAULT_MID_RUN, "--hardware", "lab",
                       "--lab", lab, "--out", out, *RUN, "--record-s", "60"],
                      env={**lab_env, "FAULT": fault})
    lines = read_until(proc, "injected", 90.0)
    t0 = time.monotonic()
    rest, _ = proc.communicate(timeout=120)
    text = "".join(lines) + rest
    assert proc.returncode == 1, text[-3000:]
    assert time.monotonic() - t0 < 40 and "Traceback" not in text, text[-3000:]  # not 60 s
    why = "shaker fault: Keysight Technologies 33522B serial MY52400001 " + why
    errors = [x for x in text.splitlines() if "metarig.rig:" in x and why in x]
    assert errors, text[-3000:]
    run = json.loads((out / "run.json").read_text())
    assert run["status"].startswith("failed: " + why) and "\n" not in run["status"]
    if fault == "silent":  # it tried, and says the output may still be on
        assert run["status"].endswith("the output may still be on: Keysight Technologies "
                                      "33522B serial MY52400001 did not take 'ABOR': "
                                      "VI_ERROR_TMO (-1073807339): Timeout expired before "
                                      "operation completed.")
    assert [p["phase"] for p in run["phases"]][-2:] == ["stop", "aborted"]
    # every other device told to stop; the recording complete, with the shaker's fault in it
    assert "the camera stops streaming" in text
    moved = max(i for i, m in enumerate(emu.received) if "move abs" in m)
    assert {"/1 1 stop", "/2 1 stop"} <= set(emu.received[moved:])
    _, msgs = read_mcap(out / "recording.mcap")
    faults = [s.message for _, m in msgs[T.DIAGNOSTICS.name] for s in m.status
              if s.name == "shaker" and s.message.startswith("fault: ")]
    assert faults == [run["status"].removeprefix("failed: shaker ")]
    assert msgs[T.IMAGE.name] and msgs[T.RIG_STOP.name]
