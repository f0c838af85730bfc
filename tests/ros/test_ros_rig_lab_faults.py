"""`metarig rig --hardware lab` when a device stops answering during the capture: the emulated
Zaber stages fall silent (a pulled cable) after the pulse; the stage node puts them in FAULT,
the run ends at once with one line and exit 1, every device is told to stop, and the
recording keeps everything up to that moment (read back with the `mcap` package)."""

import json
import time

import pytest

pytest.importorskip("pypylon", reason="pip install pypylon")
pytest.importorskip("pyvisa_sim", reason="pip install pyvisa-sim")

from labrig import read_mcap, read_until, start_lab_rig  # noqa: E402

from ros_nodes import topics as T  # noqa: E402


def test_stages_that_stop_answering_end_the_run_with_one_line(tmp_path, emu, lab_env,
                                                             start_node):
    proc, _, out = start_lab_rig(start_node, tmp_path, emu.port, lab_env, "--record-s", "30")
    lines = read_until(proc, "phase pulse", 90.0)
    time.sleep(0.5)
    emu.silent = True  # the controller reads and never answers
    t0 = time.monotonic()
    rest, _ = proc.communicate(timeout=60)
    text = "".join(lines) + rest
    assert proc.returncode == 1, text[-3000:]
    assert time.monotonic() - t0 < 20  # not the 30 s capture: ended by the fault
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
