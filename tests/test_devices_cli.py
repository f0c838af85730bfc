"""`metarig devices` against the emulators: the listing sees pylon's 2 emulated cameras, the
genicam wheel's producer and the pyvisa-sim generator, and fails softly where it cannot look;
`--lab` passes the example lab file against the emulated generator, Zaber stages (a pty) and
pylon camera, and fails with one clear line for another generator, a missing serial port,
limits the devices cannot meet, and a lab file that is wrong (exit 2, no traceback)."""

import json
import os
import re

os.environ.setdefault("PYLON_CAMEMU", "2")   # before pylon's transport-layer factory starts

import pytest  # noqa: E402

pytest.importorskip("pypylon", reason="pip install pypylon")
pytest.importorskip("pyvisa_sim", reason="pip install pyvisa-sim")
pytest.importorskip("harvesters", reason="pip install harvesters genicam")

from devices.camera.genicam import bundled_producer  # noqa: E402
from devices.cli import devices_main  # noqa: E402
from devices.lab import EXAMPLE, SHAKER_EMULATOR_YAML  # noqa: E402
from metarig.cli import main as metarig_main  # noqa: E402


def _lab(tmp_path, emu, *edits: tuple[str, str]):
    """The example lab file with the emulator's port, and `edits` (old, new) applied."""
    text = EXAMPLE.read_text().replace('"/dev/ttyUSB0"', f'"{emu.port}"')
    for old, new in edits:
        assert old in text, old
        text = text.replace(old, new)
    path = tmp_path / "lab.toml"
    path.write_text(text)
    return path


def _lines(capsys) -> list[str]:
    return capsys.readouterr().out.splitlines()


def test_listing_sees_the_emulated_cameras_and_generator(capsys):
    assert metarig_main(["devices", "--visa-sim"]) == 0
    out = _lines(capsys)
    n = int(os.environ["PYLON_CAMEMU"])
    assert f"pylon: {n} camera{'' if n == 1 else 's'}" in out  # PYLON_CAMEMU may be 1 or more
    assert [line.split()[0] for line in out if "[BaslerCamEmu]" in line] == \
        [f"0815-{i:04d}" for i in range(n)]
    viky = [line for line in out if line.startswith("gentl viky.cti: ")]
    assert viky and viky[0].startswith("gentl viky.cti: 3 cameras")
    i = out.index("visa @sim keysight33500b.yaml: 1 instrument")
    assert out[i + 1].split() == ["TCPIP0::emulated-33522b::inst0::INSTR"]
    assert any(line.startswith("visa (default library): ") for line in out)
    assert any(re.match(r"serial: \d+ ports?$", line) for line in out)


def test_listing_fails_softly_and_speaks_json(tmp_path, monkeypatch, capsys):
    (tmp_path / "broken.cti").write_text("not a GenTL producer")
    monkeypatch.setenv("GENICAM_GENTL64_PATH", str(tmp_path))
    assert devices_main(["--json", "--visa-library", "/no/such/libvisa.so"]) == 0
    probes = {p["kind"]: p for p in json.loads(capsys.readouterr().out)["probes"]}
    assert probes["gentl broken.cti"]["error"].startswith("not a loadable GenTL producer")
    assert len(probes["gentl viky.cti"]["found"]) == 3       # the others still looked
    bad = probes["visa /no/such/libvisa.so"]
    assert bad["error"] and "\n" not in bad["error"] and bad["found"] == []
    assert probes["pylon"]["error"] == "" and len(probes["pylon"]["found"]) >= 1


def test_the_example_lab_passes_against_the_emulators(tmp_path, emu, capsys):
    path = _lab(tmp_path, emu)
    assert devices_main(["--lab", str(path)]) == 0
    out = _lines(capsys)
    assert out[-1] == f"{path}: all 12 checks passed"
    checks = [line.split(":")[0].split() for line in out[:-1]]
    assert all(c[0] == "ok" for c in checks)
    assert [tuple(c[1:]) for c in checks] == [
        ("shaker", "opens"), ("shaker", "identity"), ("shaker", "voltage", "limit"),
        ("shaker", "dry-run", "waveform"), ("stage", "opens"), ("stage", "identity"),
        ("stage", "travel"), ("camera", "opens"), ("camera", "identity"),
        ("camera", "settings"), ("camera", "test", "frame"), ("ros", "discovery")]
    text = "\n".join(out)
    assert "33522B serial MY52400001" in text and "5 V peak" in text and "not played" in text
    assert "Basler Emulation serial 0815-0000" in text and "100 Hz, exposure 0.002 s" in text
    # nothing moved: the stages were asked for settings and positions only
    assert not [c for c in emu.received if " move " in c or c.endswith(" home")]
    assert emu.position(1, 1) == 0 and emu.position(2, 1) == 0


def test_json_report_and_a_genicam_camera(tmp_path, emu, capsys):
    path = _lab(tmp_path, emu, ('driver = "pylon"', 'driver = "genicam"'),
                ('serial = "0815-0000"', f'serial = "1"\ncti = "{bundled_producer()}"\n'
                                         'model = "Viky"'),
                ("exposure_s = 0.002\n", ""), ("frame_rate_hz = 100.0", "frame_rate_hz = 50.0"))
    assert devices_main(["--lab", str(path), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["ok"] is True and report["lab"] == str(path)
    cam = {c["what"]: c for c in report["checks"] if c["device"] == "camera"}
    assert "Viky serial 1" in cam["opens"]["detail"] and cam["identity"]["ok"]
    # no roi in the file: the whole sensor (the producer's largest, 800x800)
    assert "roi (0, 0, 800, 800), mono8 (Mono8)" in cam["settings"]["detail"]
    assert cam["test frame"]["detail"].startswith("800x800 uint8")


def _failed(out: list[str]) -> dict[str, str]:
    return {" ".join(line.split(":")[0].split()[1:]): line for line in out
            if line.startswith("FAILED ")}


def test_another_generator_and_a_missing_port_fail_with_one_line_each(tmp_path, emu, capsys):
    rigol = tmp_path / "rigol.yaml"
    rigol.write_text(SHAKER_EMULATOR_YAML.read_text().replace(
        "Keysight Technologies,33522B,MY52400001", "Rigol Technologies,DG1022Z,DG1ZA0000001"))
    path = _lab(tmp_path, emu, ('visa_library = "@sim"', 'visa_library = "rigol.yaml@sim"'),
                (f'"{emu.port}"', '"/dev/ttyNOSUCH0"'))
    assert devices_main(["--lab", str(path)]) == 1
    out = _lines(capsys)
    failed = _failed(out)
    assert set(failed) == {"shaker opens", "stage opens"}, out
    assert re.search(r"answers \*IDN\? with 'Rigol Technologies,DG1022Z.*not a Keysight 33500B",
                     failed["shaker opens"])
    assert "cannot open the stage controller's port /dev/ttyNOSUCH0" in failed["stage opens"]
    assert out[-1] == f"{path}: 2 of 7 checks FAILED"       # the camera was still checked
    assert sum(line.startswith("ok      camera") for line in out) == 4


def test_identity_and_limits_the_devices_cannot_meet(tmp_path, emu, capsys):
    path = _lab(tmp_path, emu, ('model = "33522B"', 'model = "33522B"\nserial = "MY00000007"'),
                ("m_per_v = 0.002", "m_per_v = 0.001"),
                ("sample_height_m = 0.225", "sample_height_m = 2.0\ndevice_id = 30341"),
                ("max_strain = 0.09", "max_strain = 0.5"),
                ('serial = "0815-0000"', 'serial = "0815-0000"\nmodel = "acA1920"'))
    assert devices_main(["--lab", str(path)]) == 1
    failed = _failed(_lines(capsys))
    assert set(failed) == {"shaker identity", "shaker dry-run waveform", "stage identity",
                           "stage travel", "camera identity"}, failed
    assert "serial 'MY52400001', not 'MY00000007'" in failed["shaker identity"]
    assert "peak 10 V exceeds the drive limit 5 V" in failed["shaker dry-run waveform"]
    assert "bottom stage reports device id 99999 and top stage reports device id 99999, the " \
           "lab file names 30341" in failed["stage identity"]
    assert "max_strain puts the bottom stage at 10498688 microsteps, outside its travel " \
           "0..10000000" in failed["stage travel"]
    assert "not a acA1920" in failed["camera identity"]


def test_a_wrong_lab_file_is_one_line_and_exit_2(tmp_path, capsys):
    path = tmp_path / "lab.toml"
    path.write_text('[stage]\ndriver = "zaber"\nport = "/dev/ttyUSB0"\nmax_strain = 0.9\n')
    assert devices_main(["--lab", str(path)]) == 2
    cap = capsys.readouterr()
    assert cap.out == "" and cap.err == (f"metarig devices: {path}: [stage] max_strain: 0.9 is "
                                         "above the maximum 0.5 (largest accepted compressive "
                                         "strain)\n")
