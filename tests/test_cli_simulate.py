"""`metarig simulate` end to end in a subprocess: files written and read back, clear errors.

The refusals of bad flags call `metarig`'s main() in this process (a subprocess costs ~2 s of
start-up each); the end-to-end run and the unknown command stay real processes."""

import json
import signal
import subprocess
import sys

import numpy as np
import pytest


def _run(*args, timeout=600):
    return subprocess.run([sys.executable, "-m", "metarig", *args], capture_output=True, text=True,
                          timeout=timeout)


def _main(capsys, *args):
    """`metarig ARGS` in this process: (exit code, stderr). An exception that the command does
    not turn into its one-line error fails the test (a subprocess printed a Traceback)."""
    from metarig.cli import main
    from metarig.signals import STOP_SIGNALS

    capsys.readouterr()
    handlers = {sig: signal.getsignal(sig) for sig in STOP_SIGNALS}  # main() sets its own
    try:
        rc = main(list(args))
    except SystemExit as exc:  # argparse's refusals
        rc = exc.code
    finally:
        for sig, handler in handlers.items():
            signal.signal(sig, handler)
    return rc, capsys.readouterr().err


def test_simulate_writes_summary_trajectory_design_and_plots(tmp_path):
    out = tmp_path / "run"
    r = _run("simulate", "--nx", "8", "--ny", "6", "--amplitude", "0.002", "--out", str(out))
    assert r.returncode == 0, r.stderr
    summary = json.loads((out / "summary.json").read_text())
    for key in ("t_f_s", "target_ke_mean_J", "total_ke_mean_J", "target_blocks", "solver"):
        assert key in summary
    assert summary["t_f_s"] == pytest.approx(2 / 30)
    assert summary["solver"]["num_accepted_steps"] > 0
    with np.load(out / "trajectory.npz") as f:
        t, q, qdot = f["t"], f["q"], f["qdot"]
    assert t.shape == (200,) and q.shape == (200, 48, 3) and qdot.shape == q.shape
    assert t.dtype == np.float64 and t[0] == 0.0 and t[-1] == pytest.approx(2 / 30, rel=1e-12)
    # the driven units follow the pulse u_in(t) in metres (SI), into the specimen (+x)
    u_in = np.where((t > 0.1 / 30) & (t < 1.1 / 30), 0.001 * (1 - np.cos(2 * np.pi * 30 * (t - 0.1 / 30))), 0)
    # (the default solve runs in float32: 1e-9 m)
    np.testing.assert_allclose(q[:, summary["input_units"], 0], np.stack([u_in] * 2, axis=1), atol=1e-9)
    # mean target KE recomputed independently from the file (masses from design polygons)
    design = json.loads((out / "design.json").read_text())
    polys = np.asarray(design["polygons_m"])
    x, y = polys[..., 0], polys[..., 1]
    area = 0.5 * np.abs(np.sum(x * np.roll(y, -1, 1) - np.roll(x, -1, 1) * y, axis=1))
    m = 6.18 * area
    ids = summary["target_blocks"]
    ke_lin = 0.5 * m[ids] * (qdot[:, ids, 0] ** 2 + qdot[:, ids, 1] ** 2)
    assert ke_lin.sum(axis=1).mean() <= summary["target_ke_mean_J"] * (1 + 1e-9)
    assert ke_lin.sum(axis=1).mean() >= 0.5 * summary["target_ke_mean_J"]
    for png in ("ke_map.png", "energy_components.png", "line_peak_ke.png"):
        assert (out / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize("args, message", [
    (["--nx", "0"], "--nx must be at least 2"),  # was the default 24x16, silently
    (["--design", "does-not-exist.json"], "does not exist"),
    (["--amplitude", "-0.01"], "amplitude"),
    (["--precompression", "0.02"], "no stages"),
    (["--nx", "30", "--preset", "kagome-20x12", "--bias-angle-deg", "20"], "no bias angle"),
])
def test_bad_inputs_give_a_clear_error_and_no_traceback(tmp_path, capsys, args, message):
    rc, err = _main(capsys, "simulate", "--out", str(tmp_path / "x"), *args)
    assert rc == 2
    assert message in err
    assert "Traceback" not in err


@pytest.mark.parametrize("args, message", [
    (["--nx", "8", "--ny", "0"], "--ny must be at least 2 (a lattice needs 2x2 units), got 0"),
    (["--nx", "1", "--ny", "6"], "--nx must be at least 2"),
    (["--task", ""], "--task is empty"),
    (["--solver", "dopri5", "--rtol", "-1"], "--rtol must be a finite number >= 0"),
])
def test_zero_or_empty_values_are_refused_not_taken_for_the_default(tmp_path, capsys, args,
                                                                     message):
    """0 and "" were read as "not given" (the preset's size, no task); now they are refused in
    one line before anything is simulated or written."""
    from design_engine.commands.simulate import modes_main, simulate_main

    for main, name in ((simulate_main, "simulate"), (modes_main, "modes")):
        out = tmp_path / name
        if main is modes_main and "--solver" in args:
            continue  # modes has no solver flags
        assert main([*args, "--out", str(out), *(["--quiet"] if name == "simulate" else [])]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith(f"metarig {name}: error: "), err
        assert message in err[0] and not out.exists()


def test_one_of_nx_ny_with_a_task_is_honoured():
    """--task with only --nx (or --ny) resizes that side and keeps the task's other one (it was
    dropped, silently): the lattice of the scene that `simulate` and `modes` would run."""
    import argparse

    from design_engine.commands.simulate import _build, _scene_args

    p = argparse.ArgumentParser()
    _scene_args(p)

    def shape(*size):
        return _build(p.parse_args(["--task", "focusing-demo", *size])).lattice.shape

    assert shape() == (8, 6)  # the task file's size
    assert shape("--nx", "6") == (6, 6) and shape("--ny", "4") == (8, 4)
    assert shape("--nx", "5", "--ny", "3") == (5, 3)


@pytest.mark.parametrize("count", ["-1", "0", "two"])
def test_modes_refuses_a_count_that_is_not_positive(capsys, count):
    rc, err = _main(capsys, "modes", "--nx", "4", "--ny", "3", "--count", count)
    assert rc == 2 and "--count" in err and "Traceback" not in err


def test_unknown_preset_and_command(capsys):
    rc, err = _main(capsys, "simulate", "--preset", "nope")
    assert rc == 2 and "invalid choice" in err
    r = _run("frobnicate", timeout=60)  # a real process: its exit status
    assert r.returncode == 2 and "unknown command" in r.stderr


def test_design_file_round_trip(tmp_path):
    from design_engine.design.design_io import load_design, save_design
    from design_engine.physics.lattice import periodic_design, quads

    lat = quads(4, 3)  # the next test's lattice: the same (eager) geometry programs
    x = periodic_design(lat, 0.4) + np.random.default_rng(0).uniform(-0.2, 0.2, lat.n_design)
    path = save_design(tmp_path / "d.json", lat, x)
    lat2, x2 = load_design(path)
    assert lat2.shape == (4, 3) and lat2.spacing == lat.spacing
    np.testing.assert_allclose(x2, x, rtol=0, atol=1e-12)
    assert len(json.loads(path.read_text())["polygons_m"]) == 12


def test_a_cut_or_binary_design_file_is_refused_naming_it(tmp_path):
    from design_engine.design.design_io import load_design, save_design
    from design_engine.physics.geometry import InvalidDesignError
    from design_engine.physics.lattice import periodic_design, quads

    lat = quads(4, 3)
    text = save_design(tmp_path / "d.json", lat, periodic_design(lat, 0.4)).read_bytes()
    for name, data in (("cut.json", text[:len(text) // 2]), ("binary.json", b"\x89PNG\xff\xfe")):
        (tmp_path / name).write_bytes(data)
        with pytest.raises(InvalidDesignError, match=f"design file {tmp_path / name} is not "
                           "readable JSON") as e:
            load_design(tmp_path / name)
        assert "\n" not in str(e.value)


@pytest.mark.slow
def test_a_precompressed_scene_starts_static_unless_ramp_is_asked_for(tmp_path):
    """The default starts the pulse from the static equilibrium (at rest at the first sample);
    --ramp simulates the stages closing, whose motion is still there when the pulse starts."""
    runs = {}
    for mode in ("static", "ramp"):
        out = tmp_path / mode
        args = ["simulate", "--preset", "protection-24x18", "--nx", "8", "--ny", "8",
                "--precompression", "0.03", "--amplitude", "0.002", "--out", str(out)]
        r = _run(*args, *(["--ramp"] if mode == "ramp" else []))
        assert r.returncode == 0, r.stderr
        summary = json.loads((out / "summary.json").read_text())
        assert summary["precompression"] == mode
        with np.load(out / "trajectory.npz") as f:
            runs[mode] = np.abs(f["qdot"][0, :, :2]).max(), np.abs(f["qdot"][0, :, 2]).max()
    # at the first sample: float32 rounding of the static start (2e-5 m/s, 7e-3 rad/s)
    # against the ramp's own motion (2e-2 m/s, 1.4 rad/s)
    assert runs["static"][0] < 1e-4 and runs["static"][1] < 0.05
    assert runs["ramp"][0] > 100 * runs["static"][0] and runs["ramp"][1] > 20 * runs["static"][1]
