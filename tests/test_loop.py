"""`metarig loop`: the plan's rig flags, the material carried between rounds, one-line refusals,
and (slow) one small round end to end on the simulated rig, then resumed."""

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from design_engine.physics.material_file import read_material_file, save_material
from ros_nodes.logic.closed_loop import (LoopError, LoopPlan, carried_material,
                                         common_stiffness_scale, load_plan_task, rig_arguments)

ROOT = Path(__file__).resolve().parents[1]


def _metarig(*argv, timeout=900):
    return subprocess.run([sys.executable, "-m", "metarig", *argv], cwd=ROOT,
                          capture_output=True, text=True, timeout=timeout)


def _flag(args, name):
    return args[args.index(name) + 1]


def test_rig_arguments_follow_the_task():
    task = load_plan_task(LoopPlan(task="focusing-demo", out=Path("unused")))
    args = rig_arguments(task, ("--perturb", "0.2", "--seed", "5"))
    scene = next(iter(task.scenes.values()))
    assert _flag(args, "--scene") == "focusing-24x16"
    assert float(_flag(args, "--amplitude")) == pytest.approx(0.002)  # the task's 2 mm pulse
    assert float(_flag(args, "--frequency")) == pytest.approx(30.0)
    # the capture covers the pre-trigger and the task's whole window after the pulse start
    window_end_s = (scene.window_start + scene.window) / 1e3
    assert float(_flag(args, "--record-s")) >= 0.005 + window_end_s
    # the frame holds the undeformed 8x6 sample (15 mm pitch)
    m_per_px = float(_flag(args, "--m-per-px"))
    assert 480 * m_per_px >= 8 * 0.015 and 360 * m_per_px >= 6 * 0.015
    assert args[-4:] == ["--perturb", "0.2", "--seed", "5"]
    own = rig_arguments(task, ("--m-per-px", "5e-4"))
    assert own.count("--m-per-px") == 1 and "--width" not in own


@pytest.mark.parametrize("flag", ["--design", "--scene", "--material", "--amplitude"])
def test_rig_arguments_refuse_what_the_loop_sets(flag):
    task = load_plan_task(LoopPlan(task="focusing-demo", out=Path("unused")))
    with pytest.raises(LoopError, match=flag):
        rig_arguments(task, (flag, "x"))


def test_identification_experiment_is_the_same_rig_with_a_short_pulse():
    """The identification experiment differs from the task's only in its input and capture: the
    same scene, frame and specimen flags (so the same sample), a 10 ms pulse, 150 ms capture."""
    from ros_nodes.logic.closed_loop import IDENTIFY_FREQUENCY_HZ, IDENTIFY_RECORD_S

    task = load_plan_task(LoopPlan(task="focusing-demo", out=Path("unused")))
    specimen = ("--perturb", "0.2", "--seed", "5", "--specimen-friction-hz", "1")
    args = rig_arguments(task, specimen)
    ident = rig_arguments(task, specimen, identify=True)
    assert float(_flag(ident, "--frequency")) == IDENTIFY_FREQUENCY_HZ == 100.0
    assert float(_flag(ident, "--amplitude")) < float(_flag(args, "--amplitude"))
    assert float(_flag(ident, "--record-s")) == pytest.approx(IDENTIFY_RECORD_S)
    assert float(_flag(ident, "--record-s")) > float(_flag(args, "--record-s"))
    input_flags = {"--amplitude", "--frequency", "--record-s"}
    for a in (args, ident):
        assert len(a) % 2 == 0
    same = {k: v for k, v in zip(args[::2], args[1::2]) if k not in input_flags}
    assert same == {k: v for k, v in zip(ident[::2], ident[1::2]) if k not in input_flags}
    longer = rig_arguments(task, ("--pre-trigger-s", "0.05"), identify=True)
    assert float(_flag(longer, "--record-s")) == pytest.approx(IDENTIFY_RECORD_S + 0.045)


@pytest.mark.parametrize("k, warm, seed, expected", [
    (1, True, None, []),
    (1, True, 3, ["--seed", "3"]),
    (2, True, 3, ["--initial", "LOOP/round-1/design/design.json"]),
    (3, True, None, ["--initial", "LOOP/round-2/design/design.json"]),
    (2, False, 3, ["--seed", "3"]),
    (2, False, None, []),
])
def test_each_round_designs_from_the_design_before(tmp_path, k, warm, seed, expected):
    from ros_nodes.logic.closed_loop import _Round

    plan = LoopPlan(task="focusing-demo", out=tmp_path, rounds=3, warm_start=warm,
                    design_seed=seed)
    start = _Round(plan, None, k, [], []).start()
    assert start == [a.replace("LOOP", str(tmp_path)) for a in expected]


def test_a_design_run_starts_from_a_given_design(tmp_path):
    """`metarig design --initial` (what round k > 1 runs): the task's initial design and every
    scene's design are the file's; a design of another lattice is refused."""
    from design_engine.design.design_io import save_design
    from design_engine.design.task import TaskError, load_task
    from design_engine.physics.lattice import periodic_design, quads

    nominal = load_task("focusing-demo")
    x = nominal.initial_design + np.random.default_rng(0).normal(0.0, 0.2,
                                                                 nominal.initial_design.size)
    path = save_design(tmp_path / "d.json", nominal.lattice, x)
    task = load_task("focusing-demo", initial=path)
    np.testing.assert_allclose(task.initial_design, x, atol=1e-9)
    for scene in task.scenes.values():
        np.testing.assert_allclose(np.asarray(scene.design), x, atol=1e-9)
    assert task.document["initial"]["design_file"] == str(path)
    other = save_design(tmp_path / "o.json", quads(6, 4), periodic_design(quads(6, 4), 0.4))
    with pytest.raises(TaskError, match="quads 6x4 design, the task's lattice is quads 8x6"):
        load_task("focusing-demo", initial=other)


def test_rig_capture_covers_a_longer_pre_trigger():
    task = load_plan_task(LoopPlan(task="focusing-demo", out=Path("unused")))
    short = float(_flag(rig_arguments(task, ()), "--record-s"))
    longer = float(_flag(rig_arguments(task, ("--pre-trigger-s", "0.05")), "--record-s"))
    assert longer == pytest.approx(short + 0.045, abs=1.5e-3)


def test_a_design_of_another_lattice_is_refused(tmp_path):
    from design_engine.design.design_io import save_design
    from design_engine.physics.lattice import periodic_design, quads
    from ros_nodes.logic.closed_loop import check_design_fits

    task = load_plan_task(LoopPlan(task="focusing-demo", out=Path("unused")))
    lattice = quads(6, 4)
    path = save_design(tmp_path / "d.json", lattice, periodic_design(lattice, 0.4))
    with pytest.raises(LoopError, match="6x4 design, but task focusing-demo is on a quads 8x6"):
        check_design_fits(path, task)
    (tmp_path / "bad.json").write_text("{")
    with pytest.raises(LoopError, match="not a readable design file"):
        check_design_fits(tmp_path / "bad.json", task)
    fits = quads(8, 6)
    check_design_fits(save_design(tmp_path / "ok.json", fits, periodic_design(fits, 0.4)), task)


def test_task_the_rig_cannot_measure_is_refused():
    with pytest.raises(LoopError, match="kinetic-energy"):
        load_plan_task(LoopPlan(task="spin-ccw", out=Path("unused")))


def _calibration(undetermined, correlation=None, start=None):
    """A pulse calibration of k_shear, k_bend and the damping ratio (SI), as calibration.json."""
    doc = {"parameters": {"k_shear": {"value": 1000.0, "stderr": 20.0, "unit": "N/m"},
                          "k_bend": {"value": 1e-4, "stderr": 5e-3, "unit": "N m/rad"},
                          "damping_ratio": {"value": 0.03, "stderr": 0.002, "unit": "1"}},
           "derived": {"damping_u": {"value": 0.04, "stderr": 0.003, "unit": "N s/m"},
                       "damping_theta": {"value": 5e-7, "stderr": 4e-8, "unit": "N m s"}},
           "undetermined": undetermined, "fit": ["k_shear", "k_bend", "damping_ratio"]}
    if correlation is not None:
        doc["correlation"] = correlation
    if start is not None:
        doc["start"] = start
    return doc


START = {"k_shear": 1190.0, "k_bend": 1.5e-3, "damping_ratio": 0.0186}


def test_carried_material_carries_each_stiffness_the_calibration_determined(tmp_path):
    model = save_material(tmp_path / "m.toml", {"k_bend": 1.2e-3, "k_stretch": 1.1e5},
                          {"k_bend": 1e-4})
    values, errors, dropped, _ = carried_material(model, _calibration([], start=START))
    assert values["k_shear"] == 1000.0 and errors["k_shear"] == 20.0  # determined: carried
    assert values["k_bend"] == 1e-4 and errors["k_bend"] == 5e-3
    assert values["k_stretch"] == 1.1e5  # not fitted: the model's
    assert values["density"] == 6.18  # not in the model file: the default's
    assert values["damping_u"] == 0.04 and values["damping_theta"] == 5e-7
    assert "damping_ratio" not in values  # the coefficients it gives are carried instead
    assert dropped == []
    save_material(tmp_path / "next.toml", values, errors)  # a valid material file
    assert read_material_file(tmp_path / "next.toml")[0] == values


def test_stiffnesses_determined_only_together_are_carried_as_one_common_scale(tmp_path):
    """k_shear determined, k_bend not (independent errors): both move by one factor, the
    precision-weighted mean of their log changes, so the model keeps its k_bend / k_shear."""
    model = save_material(tmp_path / "m.toml", {"k_shear": 1190.0, "k_bend": 1.5e-3,
                                                "k_stretch": 1.1e5})
    cal = _calibration(["k_bend", "damping_ratio"], start=START)
    values, errors, dropped, _ = carried_material(model, cal)
    x = np.log([1000.0 / 1190.0, 1e-4 / 1.5e-3])
    w = 1.0 / np.array([20.0 / 1000.0, 5e-3 / 1e-4]) ** 2
    s = math.exp(float(w @ x / w.sum()))
    assert values["k_shear"] == pytest.approx(1190.0 * s, rel=1e-12)
    assert values["k_bend"] == pytest.approx(1.5e-3 * s, rel=1e-12)
    assert values["k_bend"] / values["k_shear"] == pytest.approx(1.5e-3 / 1190.0, rel=1e-12)
    assert values["k_stretch"] == 1.1e5  # not fitted: not scaled
    # the stated error: no smaller than the best single stiffness's relative error
    assert errors["k_shear"] / values["k_shear"] == pytest.approx(0.02, rel=1e-12)
    assert errors["k_bend"] / values["k_bend"] == pytest.approx(0.02, rel=1e-12)
    assert dropped == ["damping_ratio", "damping_theta", "damping_u"]
    assert values["damping_ratio"] == 0.0186  # undetermined: the model's ratio, which gives
    assert "damping_u" not in values  # the coefficients from the carried stiffnesses
    save_material(tmp_path / "next.toml", values, errors)
    assert read_material_file(tmp_path / "next.toml")[0] == values


def test_the_common_scale_follows_the_fits_correlation():
    """With k_shear and k_bend correlated at -0.995 (the identification pulse's fits), the
    scale is the point of the common-scale line that the fit's covariance makes most likely:
    the Mahalanobis distance to the fit is smallest there (checked on a fine scan), and it is
    not k_shear's own change."""
    rho = -0.995
    corr = [[1.0, rho, 0.0], [rho, 1.0, 0.0], [0.0, 0.0, 1.0]]
    sc = common_stiffness_scale(_calibration(["k_bend"], correlation=corr, start=START))
    x = np.log([1000.0 / 1190.0, 1e-4 / 1.5e-3])
    sd = np.array([0.02, 50.0])
    cinv = np.linalg.inv(np.array([[1.0, rho], [rho, 1.0]]) * np.outer(sd, sd))
    t = np.linspace(x[0] - 0.05, x[0] + 0.05, 200001)
    d = x[None, :] - t[:, None]
    best = t[np.argmin(np.einsum("ti,ij,tj->t", d, cinv, d))]
    assert math.log(sc["value"]) == pytest.approx(best, abs=1e-6)
    # the valley moves it below k_shear's own change (k_bend's fit lies below the line)
    assert math.log(sc["value"]) < x[0] - 5e-4
    assert sc["log_stderr_on_line"] < 0.02 <= sc["log_stderr"]
    assert sc["names"] == ["k_shear", "k_bend"] and sc["start"] == {"k_shear": 1190.0,
                                                                      "k_bend": 1.5e-3}


def test_a_determined_damping_ratio_beside_a_common_scale_is_carried_as_the_ratio(tmp_path):
    model = save_material(tmp_path / "m.toml", {"damping_u": 0.05, "damping_theta": 6e-7})
    values, errors, dropped, _ = carried_material(model, _calibration(["k_bend"], start=START))
    assert values["damping_ratio"] == 0.03 and errors["damping_ratio"] == 0.002
    assert "damping_u" not in values and "damping_theta" not in values  # the ratio gives them
    assert dropped == []
    save_material(tmp_path / "next.toml", values, errors)
    assert read_material_file(tmp_path / "next.toml")[0] == values


@pytest.mark.parametrize("undetermined", [[], ["k_shear", "k_bend"]])
def test_no_common_scale_unless_determined_only_in_combination(undetermined):
    assert common_stiffness_scale(_calibration(undetermined, start=START)) is None


def test_no_common_scale_for_a_single_fitted_stiffness():
    cal = _calibration([], start=START)
    del cal["parameters"]["k_bend"]
    cal["fit"].remove("k_bend")
    assert common_stiffness_scale(cal) is None
    values, _, _, _ = carried_material(None, cal)
    assert values["k_shear"] == 1000.0


def test_the_common_scale_starts_from_the_model_where_the_calibration_gives_no_start(tmp_path):
    model = save_material(tmp_path / "m.toml", {"k_shear": 1190.0, "k_bend": 1.5e-3})
    with_start, _, _, _ = carried_material(model, _calibration(["k_bend"], start=START))
    without, _, _, _ = carried_material(model, _calibration(["k_bend"]))
    assert without["k_shear"] == pytest.approx(with_start["k_shear"], rel=1e-12)
    assert common_stiffness_scale(_calibration(["k_bend"])) is None  # no start known


def test_carried_material_drops_damping_derived_from_an_undetermined_ratio():
    from design_engine.physics.material import default_si

    values, _, dropped, _ = carried_material(None, _calibration(["damping_ratio"]))
    assert values == {**default_si(), "k_shear": 1000.0, "k_bend": 1e-4}  # the ratio: default
    assert set(dropped) == {"damping_ratio", "damping_u", "damping_theta"}


def test_a_calibration_that_determined_nothing_leaves_a_complete_model(tmp_path):
    from design_engine.physics.material import default_si

    model = save_material(tmp_path / "m.toml", {"k_shear": 900.0}, {"k_shear": 30.0})
    undetermined = ["k_shear", "k_bend", "damping_ratio"]
    values, errors, dropped, _ = carried_material(model, _calibration(undetermined))
    assert values == {**default_si(), "k_shear": 900.0} and errors == {"k_shear": 30.0}
    save_material(tmp_path / "next.toml", values, errors)  # loadable: not an empty file
    assert read_material_file(tmp_path / "next.toml")[0] == values


@pytest.mark.parametrize("argv, text", [
    (["no-such-task"], "task no-such-task"),
    (["focusing-demo", "--design", "missing.json"], "--design missing.json: no such file"),
    (["focusing-demo", "--", "--scene", "focusing-24x16"], "--scene"),
])
def test_bad_inputs_get_one_line(tmp_path, argv, text):
    r = _metarig("loop", *argv[:1], "--out", str(tmp_path / "loop"), *argv[1:], timeout=120)
    assert r.returncode == 2
    assert text in r.stderr and "Traceback" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "loop" / "round-1").exists()


STEP_FILES = {
    "design": ["design.json", "history.json", "run.json", "step.json"],
    "rig": ["recording.mcap", "run.json", "summary.json", "comparison.rrd", "tracks.npz",
            "simulated.npz", "design.json", "calibration.json", "step.json"],
    "objective": ["objective.json", "target_ke.npz", "step.json"],
    "identify": ["recording.mcap", "run.json", "step.json"],
    "calibrate": ["calibration.json", "material.toml", "calibration.png", "step.json"],
}


@pytest.mark.slow  # one round: a 2-evaluation design, two rig runs, tracking, a calibration
def test_one_round_end_to_end_then_resumed(tmp_path):
    out = tmp_path / "loop"
    argv = ["loop", "focusing-demo", "--out", str(out), "--rounds", "1", "--max-evals", "2",
            "--workers", "2", "--", "--perturb", "0.2", "--seed", "576"]
    r = _metarig(*argv)
    assert r.returncode == 0, r.stderr[-2000:]
    round_dir = out / "round-1"
    for step, names in STEP_FILES.items():
        missing = [n for n in names if not (round_dir / step / n).is_file()]
        assert not missing, f"{step}: {missing}"
    assert (out / "loop.rrd").stat().st_size > 1000
    doc = json.loads((out / "loop.json").read_text())
    (rnd,) = doc["rounds"]
    assert rnd["design"] == str(round_dir / "design" / "design.json")
    for key in ("predicted_objective_J", "measured_objective_J"):
        assert np.isfinite(rnd[key]) and rnd[key] > 0
    # the sample differs from the model, but not by orders of magnitude
    assert 0.2 < rnd["measured_objective_J"] / rnd["predicted_objective_J"] < 5
    objective = json.loads((round_dir / "objective" / "objective.json").read_text())
    ke = np.load(round_dir / "objective" / "target_ke.npz")
    assert ke["t_s"].shape == ke["target_ke_measured_J"].shape
    # the objective is the mean over the task's window, within the recorded target energy
    assert 0 < objective["measured_J"] <= ke["target_ke_measured_J"].max()
    cal = rnd["calibrated_material"]
    assert cal["parameters"] and all("stderr" in p for p in cal["parameters"].values())
    assert "[loop] round 1/1: calibrate: done in" in r.stderr
    # the calibration fitted the identification experiment, the 100 Hz pulse on the same sample
    assert rnd["calibrated_from"] == str(round_dir / "identify")
    ident = json.loads((round_dir / "identify" / "step.json").read_text())["command"]
    assert float(_flag(ident, "--frequency")) == 100.0
    assert _flag(ident, "--seed") == "576" and _flag(ident, "--perturb") == "0.2"

    stamps = {p: p.stat().st_mtime_ns for p in round_dir.rglob("*") if p.is_file()}
    again = _metarig(*argv)
    assert again.returncode == 0, again.stderr[-2000:]
    assert again.stderr.count("done already") == 5
    assert "done in" not in again.stderr  # no step ran
    assert {p: p.stat().st_mtime_ns for p in round_dir.rglob("*") if p.is_file()} == stamps
    again_doc = json.loads((out / "loop.json").read_text())
    assert again_doc["rounds"][0]["measured_objective_J"] == rnd["measured_objective_J"]


def test_an_interrupted_step_is_redone_not_trusted(tmp_path):
    """A step folder without its `step.json` (an interrupted step) is not taken as done: the
    loop recomputes it (here the objective of a run folder that holds no recording fails,
    which shows that it was attempted)."""
    out = tmp_path / "loop"
    round_dir = out / "round-1"
    (round_dir / "design").mkdir(parents=True)
    (round_dir / "design" / "design.json").write_text("{}")
    (round_dir / "design" / "step.json").write_text(json.dumps({"command": None}))
    (round_dir / "rig").mkdir()
    (round_dir / "rig" / "step.json").write_text(json.dumps({"command": None}))
    (round_dir / "objective").mkdir()  # interrupted: no step.json
    r = _metarig("loop", "focusing-demo", "--out", str(out), "--rounds", "1", timeout=300)
    assert r.returncode == 2
    assert "design: done already" in r.stderr and "rig (experiment" in r.stderr
    assert "objective (measured and predicted) ..." in r.stderr
    assert "objective of" in r.stderr.strip().splitlines()[-1]


def test_loop_rrd_shows_the_rounds_side_by_side(tmp_path):
    """`loop.rrd`: per round its design and its measured and predicted target energy, a view
    of each per round, and the table of the rounds."""
    from rerun.chunk import RrdReader

    from ros_nodes.logic.closed_loop import OBJECTIVE
    from ros_nodes.logic.loop_record import write_loop_rrd

    rng = np.random.default_rng(0)
    square = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float64) * 0.01
    rounds = []
    for k, n_t in ((1, 30), (2, 40)):
        folder = tmp_path / f"round-{k}" / OBJECTIVE
        folder.mkdir(parents=True)
        polygons = square[None] + 0.015 * np.arange(6)[:, None, None] * [1, 0]
        np.savez(folder / "target_ke.npz", t_s=np.arange(n_t) * 1e-3,
                 target_ke_measured_J=rng.random(n_t), target_ke_predicted_J=rng.random(n_t),
                 polygons_m=polygons)
        (folder / "objective.json").write_text(json.dumps({"terms": {"t": {"ids": [4, 5]}}}))
        rounds.append({"round": k, "design_objective_J": 2e-6 * k, "predicted_objective_J": 1e-6,
                       "measured_objective_J": 1.1e-6 * k, "measured_over_predicted": 1.1 * k})
    path = write_loop_rrd(tmp_path / "loop.rrd", rounds,
                          {k: tmp_path / f"round-{k}" / OBJECTIVE for k in (1, 2)})
    reader = RrdReader(path)
    (recording,) = reader.recordings()
    chunks = reader.stream(store=recording).to_chunks()
    rows = {}
    for ch in chunks:
        if not ch.is_static:
            rows[ch.entity_path] = rows.get(ch.entity_path, 0) + ch.num_rows
    for k, n_t in ((1, 30), (2, 40)):
        for side in ("measured", "predicted"):
            assert rows[f"/round-{k}/target_ke/{side}"] == n_t
    entities = {ch.entity_path for ch in chunks}
    assert {"/round-1/design", "/round-2/design", "/summary"} <= entities
    (design,) = [ch for ch in chunks if ch.entity_path == "/round-2/design"]
    colours = design.to_record_batch().column("LineStrips2D:colors").to_pylist()[0]
    assert len(colours) == 6 and colours[4] == colours[5] != colours[0]  # the target marked
    views = set()
    for b in reader.blueprints():
        for ch in reader.stream(store=b).to_chunks():
            if ch.entity_path.startswith("/view/") and ch.entity_path.count("/") == 2:
                views.add(ch.to_record_batch().column(
                    "ViewBlueprint:space_origin").to_pylist()[-1][0])
    assert {"round-1/design", "round-2/design", "round-2/target_ke", "summary"} <= views
    assert not list(tmp_path.glob(".loop.rrd*"))  # the temporary file was renamed


def test_a_folder_resumes_only_with_its_own_settings(tmp_path):
    from ros_nodes.logic.closed_loop import check_same_settings

    first = LoopPlan(task="focusing-demo", out=tmp_path, max_evals=3, rig_args=("--seed", "5"))
    check_same_settings(first)
    check_same_settings(first)  # the same settings: resume
    check_same_settings(LoopPlan(task="focusing-demo", out=tmp_path, max_evals=3, rounds=4,
                                 workers=1, rig_args=("--seed", "5")))  # more rounds: fine
    with pytest.raises(LoopError, match=r"other settings \(max_evals, rig_args: 3, \['--seed', "
                                        r"'5'\]\)"):
        check_same_settings(LoopPlan(task="focusing-demo", out=tmp_path, max_evals=4,
                                     rig_args=("--seed", "6")))
