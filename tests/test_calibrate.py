"""`metarig calibrate`: material constants recovered from simulated characterisation tests.

Truth: the nominal material with stiffnesses and damping perturbed by 20 %; noise: 0.02 N on
the hinge-test forces (`characterisation.FORCE_NOISE_N`), 1e-3 rad on the tracked rotation at
960 fps (`ROTATION_NOISE_RAD`). Tolerances are stated per test; every recovered value must also
lie within 3 of its reported standard errors of the truth.
"""

import functools
import json
from pathlib import Path

import numpy as np
import pytest

from design_engine.calibration.fit import (CalibrationError, LARGE_SD, covariance,
                                           start_damping_ratio, to_si)
from design_engine.calibration.hinge import fit_hinge, hinge_sample, read_hinge_file
from design_engine.calibration.oscillation import fit_oscillation, log_decrement, oscillation_sample
from design_engine.calibration.pulse import WINDOWS, fit_pulse, pose_weights, window_frames
from design_engine.physics.material import reference_damping
from design_engine.physics.material_file import SI_UNITS
from hardware_sim import characterisation as ch
from ros_nodes.cli_calibrate import calibrate_main

ROOT = Path(__file__).resolve().parents[1]
FACTORS = {"k_stretch": 1.2, "k_shear": 0.8, "k_bend": 1.2}


def _spec_damped(m, lattice, zeta, **stiffness_factors):
    """`m` with stiffnesses scaled and c_u, c_theta set by spec 6.3 from `zeta`."""
    m = m.scaled(stiffness_factors)
    c_u, c_t = reference_damping(lattice, zeta, m.density, m.k_shear, m.k_bend)
    return m.replaced(damping_u=c_u, damping_theta=c_t)


def _truth_si(m, name):
    return to_si(name, float(getattr(m, name)))


@pytest.fixture(scope="module")
def hinge_files(tmp_path_factory):
    true = hinge_sample().material.scaled(FACTORS)
    d = tmp_path_factory.mktemp("hinge")
    return true, ch.hinge_tests(true, d, n_points=50, seed=1)


def test_hinge_files_have_the_instron_layout(hinge_files):
    _, paths = hinge_files
    lines = paths[0].read_text().splitlines()
    assert lines[2] == "Time (s),Extension (m),Load (N)" and "test=tension" in lines[1]
    a = np.loadtxt(paths[0], delimiter=",", skiprows=3)
    assert a.shape == (50, 3) and a[-1, 1] == pytest.approx(1.05e-3)


def test_hinge_calibration_recovers_the_stiffnesses(hinge_files, tmp_path, capsys):
    """3 tests x 50 points, 0.02 N noise: k_shear and k_bend within 2 %, k_stretch (seen
    mostly by the tension test) within 6 %; errors within 3 stderr."""
    true, paths = hinge_files
    out = tmp_path / "cal"
    assert calibrate_main([*map(str, paths), "--out", str(out)]) == 0
    doc = json.loads((out / "calibration.json").read_text())
    assert set(doc) >= {"parameters", "residual", "source"} and doc["kind"] == "hinge"
    assert doc["residual"] == pytest.approx(ch.FORCE_NOISE_N, rel=0.3)  # residual = noise
    for name, tol in (("k_shear", 0.02), ("k_bend", 0.02), ("k_stretch", 0.06)):
        p = doc["parameters"][name]
        t = _truth_si(true, name)
        assert p["unit"] == SI_UNITS[name]
        assert abs(p["value"] / t - 1) < tol, (name, p, t)
        assert abs(p["value"] - t) < 3 * p["stderr"], (name, p, t)
    assert (out / "material.toml").exists() and (out / "calibration.png").stat().st_size > 0
    from design_engine.physics.material_file import load_material_file

    vals, errs = load_material_file(out / "material.toml")
    assert vals["k_shear"] == pytest.approx(doc["parameters"]["k_shear"]["value"])
    assert errs["k_shear"] == pytest.approx(doc["parameters"]["k_shear"]["stderr"])


def test_a_parameter_the_test_does_not_see_gets_a_large_stderr(hinge_files):
    """Shear test alone: k_stretch barely changes the shear force."""
    true, paths = hinge_files
    recs = [read_hinge_file(p) for p in paths if "shear" in p.name]
    fit = fit_hinge(recs, ("k_stretch", "k_shear"))
    assert fit.stderr["k_stretch"] > 0.5 * fit.values["k_stretch"]  # > 50 %: not determined
    assert "k_stretch" in fit.undetermined and "k_shear" not in fit.undetermined
    t = _truth_si(true, "k_shear")
    assert abs(fit.values["k_shear"] - t) < 3 * fit.stderr["k_shear"]


@pytest.fixture(scope="module")
def oscillation(tmp_path_factory):
    sample = oscillation_sample()
    m = sample.material
    zeta = 0.8 * start_damping_ratio(m, sample.lattice)  # spec 6.3 truth: zeta and k_bend
    true = _spec_damped(m, sample.lattice, zeta, k_bend=1.2)
    cfg = ch.OscillationConfig(n_frames=300)
    path = ch.write_oscillation(tmp_path_factory.mktemp("osc") / "tracks.npz",
                                ch.free_oscillation(true, cfg), cfg)
    clean = ch.free_oscillation(true, ch.OscillationConfig(n_frames=300, noise_rad=0.0,
                                                           noise_m=0.0))
    return true, path, clean, zeta


def test_oscillation_damping_by_log_decrement_and_by_fit(oscillation, tmp_path):
    """300 frames at 960 fps, 1e-3 rad noise: the hand method (6 usable peaks) within 10 % of
    the noise-free curve's and of the fitted curve's; the engine fit within 2 % (zeta, k_bend)
    and within 3 stderr."""
    true, path, clean, zeta = oscillation
    out = tmp_path / "cal"
    assert calibrate_main([str(path), "--out", str(out)]) == 0
    doc = json.loads((out / "calibration.json").read_text())
    assert doc["kind"] == "oscillation"
    ref = log_decrement(clean.t, clean.q[:, 1, 2])["damping_ratio"]
    ld = doc["log_decrement"]
    assert ld["damping_ratio"] == pytest.approx(ref, rel=0.10)
    assert ld["damping_ratio_of_fit"] == pytest.approx(ref, rel=0.01)  # fit: the true curve
    for name, t in (("damping_ratio", zeta), ("k_bend", _truth_si(true, "k_bend"))):
        p = doc["parameters"][name]
        assert abs(p["value"] / t - 1) < 0.02 and abs(p["value"] - t) < 3 * p["stderr"], (name, p, t)
    for name in ("damping_u", "damping_theta"):
        d = doc["derived"][name]
        assert abs(d["value"] / _truth_si(true, name) - 1) < 0.02, (name, d)
    assert (out / "material.toml").exists() and (out / "calibration.png").exists()


def _one_line(capsys, argv, message):
    code = calibrate_main(argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and message in err[0], err


def _hinge_text(rows, test="shear"):
    return "\n".join(["Instron", f"test={test}", "Time (s),Extension (m),Load (N)", *rows]) + "\n"


@pytest.mark.parametrize("case, message", [
    ("malformed", "is not numeric"),
    ("columns", "expected 3"),
    ("few", "a hinge fit needs"),
    ("no-test", "which hinge test"),
    ("unknown-param", "cannot fit"),
    ("mixed", "mix test kinds"),
    ("empty-fit", "--fit names no parameter"),  # was the default set, silently
])
def test_bad_hinge_and_tracks_inputs_give_one_line(case, message, tmp_path, capsys):
    good = [f"{i:.3f},{i * 1e-5:.6e},{i * 0.01:.4f}" for i in range(40)]
    f = tmp_path / "shear_run.csv"
    argv = [str(f), "--out", str(tmp_path / "o")]
    if case == "malformed":
        f.write_text(_hinge_text(good[:20] + ["1.0,abc,2.0"] + good[20:]))
    elif case == "columns":
        f.write_text(_hinge_text([r + ",7" for r in good]))
    elif case == "few":
        f.write_text(_hinge_text(good[:4]))
    elif case == "no-test":
        f = tmp_path / "run1.csv"
        f.write_text(_hinge_text(good).replace("test=shear", ""))
        argv[0] = str(f)
    elif case == "unknown-param":
        f.write_text(_hinge_text(good))
        argv += ["--fit", "k_shear,damping_u"]
    elif case == "empty-fit":
        f.write_text(_hinge_text(good))
        argv += ["--fit", " , "]
    else:
        f.write_text(_hinge_text(good))
        np.savez(tmp_path / "t.npz", t=np.zeros(3), q=np.zeros((3, 2, 3)))
        argv.insert(1, str(tmp_path / "t.npz"))
    _one_line(capsys, argv, message)
    assert not (tmp_path / "o" / "calibration.json").exists()


def test_a_tracks_file_without_a_trajectory_gives_one_line(tmp_path, capsys):
    np.savez(tmp_path / "bad.npz", x=np.zeros(3))
    _one_line(capsys, [str(tmp_path / "bad.npz"), "--out", str(tmp_path / "o")],
              "not a trajectory file")
    t = np.arange(20) / 960
    np.savez(tmp_path / "short.npz", t=t, q=np.zeros((20, 2, 3)))
    _one_line(capsys, [str(tmp_path / "short.npz"), "--out", str(tmp_path / "o")],
              "needs 50 or more")
    from metarig.trajectory import Trajectory  # a tracks file cut to half its bytes

    Trajectory.from_positions(t, np.zeros((20, 2, 3))).save_npz(tmp_path / "cut.npz")
    data = (tmp_path / "cut.npz").read_bytes()
    (tmp_path / "cut.npz").write_bytes(data[:len(data) // 2])
    _one_line(capsys, [str(tmp_path / "cut.npz"), "--out", str(tmp_path / "o")],
              "cut.npz: cannot read a trajectory")


def test_a_recording_without_poses_gives_one_line(tmp_path, capsys):
    from ros_nodes import topics as T
    from ros_nodes.logic.mcap_append import append_messages

    src = ROOT / "recordings" / "precompression-12x8" / "recording.mcap"
    (tmp_path / "r").mkdir()
    path = append_messages(src, tmp_path / "r" / "recording.mcap", {}, [],
                           replace=(T.IMAGE.name, T.CAMERA_INFO.name, T.GROUND_TRUTH.name))
    _one_line(capsys, [str(path), "--out", str(tmp_path / "o")], "neither poses nor camera frames")


def test_the_camera_calibration_of_a_run_folder_is_never_overwritten(tmp_path, capsys):
    (tmp_path / "calibration.json").write_text('{"m_per_px": 1e-4}')
    f = tmp_path / "shear.csv"
    f.write_text(_hinge_text([f"{i},{i * 1e-5},{i * 0.01}" for i in range(40)]))
    _one_line(capsys, [str(f), "--out", str(tmp_path)], "not a material calibration")


@functools.cache
def _pulse_truth(half_amplitude_m):
    """A simulated 8x6 focusing experiment under the 1 - cos pulse u = a (1 - cos 2 pi 30 t)
    (peak 2a), 1 kHz frames for 70 ms, truth by the rig's physics (Dopri8 with contact, not the
    fit's fixed-step Verlet): (specimen, frame times, t_in, u_in, q [n_t, n, 3])."""
    from hardware_sim import specimen as sp
    from hardware_sim.rig import MotionRecord, capture_times, specimen_motion

    t_in = np.arange(0.0, 0.08, 1e-4)
    u_in = half_amplitude_m * (1 - np.cos(2 * np.pi * 30 * np.clip(t_in - 0.005, 0, 1 / 30)))
    # the sample is its model here (recovery of known constants); the imperfect specimen's
    # calibration: test_pulse_calibration_of_an_imperfect_specimen_states_its_model_error
    s = sp.build(sp.SpecimenConfig(scene="focusing-24x16", nx=8, ny=6, bias_angle_deg=25.0,
                                   imperfections=sp.NOMINAL))
    times = capture_times(0.001, 0.07, 1000.0)
    q = specimen_motion(s, times, MotionRecord(t_in, u_in), None, 1000.0).q[1:]
    return s, times, t_in, u_in, q


def _simulated_pulse_fit(half_amplitude_m, fit, start_factors):
    """`_pulse_truth` with tracked-position noise `POSITION_NOISE_M` (seed 0) on u, v; the fit
    of `fit` from the nominal material scaled by `start_factors`. Returns (fit, truth)."""
    s, times, t_in, u_in, q = _pulse_truth(half_amplitude_m)
    q = q + np.random.default_rng(0).normal(0, ch.POSITION_NOISE_M, q.shape) * [1, 1, 0]
    m = s.scene.material
    fit = fit_pulse(s.scene, times, q, np.ones(q.shape[:2], bool), t_in, u_in,
                        fit=fit, start=m.scaled(start_factors))
    return fit, m


def test_pulse_calibration_recovers_k_shear_within_2_percent():
    """The README's pulse calibration on a small scene: 8x6 under a 4 mm pulse, k_shear and
    k_bend fitted from a start 20 % off. k_shear comes back within 2 % and within 3 of its
    standard errors, and the residual is the tracking noise.

    Margins (measured): k_shear off by 0.12 %, 0.6 of its stderr (0.19 %); over noise seeds
    0-3 the error stays within 0.4 % (stderr 0.2-0.3 %), so the 2 % bound is 5x any draw's
    error. The noise is seeded (numpy's generator, the same draws on every machine) and the
    fit converges to its optimum, so another CPU's rounding moves the result by orders of
    magnitude less than that slack. Noise-free the fit is within 0.06 %: the error is the
    noise, not a bias of the model. A 5 % slip in the model's k_shear fails the test (4.7 %
    off). The slow test below uses the 2 mm pulse, whose k_shear scatter over seeds reaches
    2 % (1-1.3 % stderr)."""
    fit, m = _simulated_pulse_fit(2e-3, ("k_shear", "k_bend"),
                                  {"k_shear": 1.2, "k_bend": 0.8})
    t = _truth_si(m, "k_shear")
    assert abs(fit.values["k_shear"] / t - 1) < 0.02, (fit.values["k_shear"], t)
    assert abs(fit.values["k_shear"] - t) < 3 * fit.stderr["k_shear"], (fit.stderr, t)
    assert fit.stderr["k_shear"] < 0.01 * t  # the data determine it (measured 0.19 %)
    assert fit.rms == pytest.approx(ch.POSITION_NOISE_M, rel=0.2)  # measured 0.07 % below
    # the sample is the model: the residual is the noise (estimated within 20 %), no model error
    me = fit.extra["model_error"]
    assert me["misfit_rms_m"] == 0.0 and fit.stderr == fit.extra["stderr_statistical"]
    assert me["noise_m"] == pytest.approx(ch.POSITION_NOISE_M, rel=0.2)


def test_pulse_calibration_of_an_imperfect_specimen_states_its_model_error(tmp_path):
    """A discrepant 8x6 specimen (the default imperfections: cut tolerance, ligament and
    damping scatter, thickness error, friction; `tests/discrepant.py`) under a 4 mm pulse,
    50 ms at 1 kHz, tracked-position noise 1.2e-5 m, fitted from a start 20 % off: the nominal
    model cannot explain it to its noise, the fit says so (`model_error`), and the stated
    errors cover the effective truth, the specimen's mean stiffnesses (`Specimen.effective_si`).
    Measured (noise seeds 0 and 1): k_shear 1.9 % and 1.8 % below it, with statistical
    stderrs of 0.26 % and 0.31 % alone 7.4 and 6.0 of them off (a confident wrong constant),
    stated 3.4 % and 3.1 % with the model error (0.6 of them); k_bend 15 % above, stated
    170 % and 157 % (the short quasi-static record barely sees it); misfit 11-12 um beyond
    13.4-13.8 um of noise (1.2e-5 added), reduced chi^2 1.6-1.75."""
    import dataclasses

    from discrepant import asymmetric_design, raised_cosine

    from hardware_sim import specimen as sp
    from hardware_sim.rig import MotionRecord, capture_times, specimen_motion

    cfg = sp.SpecimenConfig(scene="focusing-24x16", seed=3,
                            design_path=str(asymmetric_design(tmp_path / "design.json")))
    nominal = sp.build(dataclasses.replace(cfg, imperfections=sp.NOMINAL))
    s = sp.build(cfg)
    t_in, u_in = raised_cosine(4e-3, 0.07)
    times = capture_times(0.001, 0.05, 1000.0)
    q = specimen_motion(s, times, MotionRecord(t_in, u_in), None, 1000.0).q[1:]
    q = q + np.random.default_rng(0).normal(0, ch.POSITION_NOISE_M, q.shape) * [1, 1, 0]
    fit = fit_pulse(nominal.scene, times, q, np.ones(q.shape[:2], bool), t_in, u_in,
                        fit=("k_shear", "k_bend"),
                        start=nominal.scene.material.scaled({"k_shear": 1.2, "k_bend": 0.8}))
    me = fit.extra["model_error"]
    assert me["misfit_rms_m"] > 0.3 * me["noise_m"] and me["reduced_chi2"] > 1.1
    truth = s.effective_si()
    # the statistical errors alone would claim k_shear to a precision it is not right to
    assert abs(fit.values["k_shear"] - truth["k_shear"]) > 3 * fit.extra["stderr_statistical"][
        "k_shear"]
    for n in ("k_shear", "k_bend"):
        err = abs(fit.values[n] - truth[n])
        assert err < 3 * fit.stderr[n], (n, fit.values[n], truth[n], fit.stderr[n])
        assert me["stderr_model"][n] > fit.extra["stderr_statistical"][n]
    # and the figure is one a material file can take: k_shear is still determined
    assert fit.stderr["k_shear"] < 0.1 * fit.values["k_shear"]


def test_pose_weights_follow_the_stated_errors():
    use = np.array([[True, True, False], [True, True, True]])
    sigma = np.ones((2, 3, 3)) * 1e-5
    sigma[:, 1, :2] = 4e-5
    w = pose_weights(sigma, use)
    assert w.shape == (2, 3, 2) and np.all(w[0, 2] == 0.0)  # unused: no weight
    assert np.allclose(w[:, 0], 1.0) and np.allclose(w[:, 1], 0.25)  # median / own
    assert pose_weights(None, use) is None
    sigma[1, 2, 0] = np.nan  # a used pose without a stated error: no weighting at all
    assert pose_weights(sigma, use) is None


@pytest.mark.slow  # 25-35 s; pose_weights above is the fast check of the weights
def test_the_pulse_fit_weights_poses_by_their_stated_errors():
    """Half of the units tracked 8x worse than the others, and saying so: weighted by the
    stated errors, k_shear comes out closer than without (measured 0.15 % against 0.49 % off,
    noise seed 1) and each within 3 of its stated standard errors; the fit says whether it was
    weighted."""
    s, times, t_in, u_in, q = _pulse_truth(2e-3)
    sigma = np.full(q.shape, ch.POSITION_NOISE_M)
    sigma[:, 1::2] *= 8.0
    q = q + np.random.default_rng(1).normal(0.0, 1.0, q.shape) * sigma * [1, 1, 0]
    m = s.scene.material
    t = _truth_si(m, "k_shear")
    errs = {}
    for weighted in (False, True):
        fit = fit_pulse(s.scene, times, q, np.ones(q.shape[:2], bool), t_in, u_in,
                            fit=("k_shear",), start=m.scaled({"k_shear": 1.2}),
                            tracked_sigma=sigma if weighted else None)
        assert fit.extra["weighted_by_pose_sigma"] is weighted
        errs[weighted] = abs(fit.values["k_shear"] / t - 1)
        assert errs[weighted] < 3 * fit.stderr["k_shear"] / t, (errs, fit.stderr)
    assert errs[True] < errs[False], errs


@pytest.mark.slow
def test_pulse_calibration_recovers_perturbed_parameters():
    """A simulated 8x6 focusing experiment (2 mm pulse, 1 kHz frames, truth by the rig's
    physics), tracked-position noise 1.2e-5 m, fitted from a start 20 % off: k_shear within
    2 %, k_bend within 10 % (it is seen less), every error within 3 stderr; damping_u is
    barely seen by this short, quasi-static record and gets a large stderr."""
    fit, m = _simulated_pulse_fit(1e-3, ("k_shear", "k_bend", "damping_u"),
                                  {"k_shear": 1.2, "k_bend": 0.8, "damping_u": 1.2})
    for name, tol in (("k_shear", 0.02), ("k_bend", 0.10)):
        t = _truth_si(m, name)
        assert abs(fit.values[name] / t - 1) < tol, (name, fit.values[name], t)
        assert abs(fit.values[name] - t) < 3 * fit.stderr[name]
    assert fit.stderr["damping_u"] > 0.2 * fit.values["damping_u"]  # barely seen: large stderr
    assert abs(fit.values["damping_u"] - _truth_si(m, "damping_u")) < 3 * fit.stderr["damping_u"]
    assert fit.rms == pytest.approx(ch.POSITION_NOISE_M, rel=0.2)


@pytest.mark.slow
def test_pulse_calibration_of_a_recording_writes_its_outputs(tmp_path):
    """The focusing-12x8 sample recording end to end (ground-truth poses, measured input), from
    a start material file 20 % off: the fit comes back to the material the sample was
    recorded with, and the files say what it found."""
    from design_engine.physics.material import default_si
    from design_engine.physics.material_file import read_material_file, save_material

    run = ROOT / "recordings" / "focusing-12x8"
    # the recorded sample is the default material: no material file, no perturbation
    design = json.loads((run / "design.json").read_text())
    assert design["true_parameter_factors"] == {} and "material_si" not in design
    truth = default_si()
    start = {"k_shear": 1.2 * truth["k_shear"], "k_bend": 0.8 * truth["k_bend"]}
    save_material(tmp_path / "start.toml", start)
    out = tmp_path / "cal"
    assert calibrate_main([str(run), "--out", str(out), "--poses", "truth", "-q",
                           "--fit", "k_shear,k_bend", "--material",
                           str(tmp_path / "start.toml")]) == 0
    doc = json.loads((out / "calibration.json").read_text())
    assert doc["kind"] == "pulse" and set(doc["parameters"]) == {"k_shear", "k_bend"}
    assert doc["start"] == pytest.approx(start, rel=1e-12)
    fitted = {k: v["value"] for k, v in doc["parameters"].items()}
    # Measured: k_shear +0.36 %, k_bend -0.45 % from this start (+0.34 %, -1.25 % from the
    # default), residual rms 0.20 mm. The sample was recorded by an earlier rig physics (its
    # specimen felt the polyline of the shaker's joint states, not their spline): re-simulated
    # now from its shaker record, this 7.5 mm pulse on 12x8 ends up to 3 mm off its ground
    # truth late in the record. The fit absorbs that model error, which the statistical
    # stderrs (0.0006 % and 0.04 %) do not cover, so the bounds are relative, ~2.5x the
    # largest measured error; the stated stderrs, with the model error (measured: misfit
    # 0.20 mm beyond 10 um of noise; k_shear's value drifts by 0.31 % between the first
    # window and the whole record), do (k_shear 1.2 of them off, k_bend 0.3). The mismatch is fixed by the recording; another CPU's rounding,
    # amplified ~1e3 over the record (3 um -> 3 mm), stays orders below it.
    assert abs(fitted["k_shear"] / truth["k_shear"] - 1) < 0.01
    assert abs(fitted["k_bend"] / truth["k_bend"] - 1) < 0.03
    assert doc["residual"] < 4e-4 and doc["n_residuals"] == 51 * 94 * 2  # u, v, undriven
    assert doc["model_error"]["misfit_rms_m"] > 10 * doc["model_error"]["noise_m"]
    for n, p in doc["parameters"].items():
        assert abs(p["value"] - truth[n]) < 3 * p["stderr"], (n, p, truth[n])
        assert doc["stderr_statistical"][n] < p["stderr"]
    values, stderr = read_material_file(out / "material.toml")  # the fitted values, exactly
    assert values == {k: pytest.approx(v, rel=1e-15) for k, v in fitted.items()}
    assert stderr == {k: pytest.approx(v["stderr"], rel=1e-15)
                      for k, v in doc["parameters"].items()}
    assert (out / "calibration.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_cluster_robust_errors_equal_gauss_newton_for_noise_and_grow_for_correlated_errors():
    """Linear model y = a x + b, 200 groups of 50 points. Independent noise: the sandwich
    errors agree with Gauss-Newton (within 15 %) and cover the truth; an error shared by each
    group (a per-group offset, as a tracker bias along one unit's record): Gauss-Newton
    claims ~sqrt(50) x too much precision, the cluster-robust error does not."""
    rng = np.random.default_rng(3)
    groups = np.repeat(np.arange(200), 50)
    x = rng.normal(size=groups.size) + 0.3 * rng.normal(size=200)[groups]
    J = np.c_[x, np.ones_like(x)]
    r = rng.normal(0, 0.1, x.size)
    gn = np.sqrt(np.diag(covariance(J, r)[0]))
    cr = np.sqrt(np.diag(covariance(J, r, groups)[0]))
    assert np.allclose(cr, gn, rtol=0.15)
    shared = r + rng.normal(0, 0.1, 200)[groups]  # the residual at the LS optimum, offset per group
    shared -= J @ np.linalg.lstsq(J, shared, rcond=None)[0]
    gn = np.sqrt(np.diag(covariance(J, shared)[0]))
    cr = np.sqrt(np.diag(covariance(J, shared, groups)[0]))
    assert cr[1] > 4 * gn[1]  # the intercept sees the group offsets in full
    # over 200 repeats, the per-group offsets move the intercept by ~0.1 / sqrt(200) = 0.007
    assert cr[1] == pytest.approx(0.1 / np.sqrt(200), rel=0.3)


def test_a_direction_the_data_do_not_see_gets_the_large_standard_error():
    J = np.c_[np.linspace(0, 1, 30), np.zeros(30)]
    r = np.random.default_rng(0).normal(0, 0.01, 30)
    sd = np.sqrt(np.diag(covariance(J, r, np.arange(30) // 3)[0]))
    assert sd[0] < 0.1 and sd[1] == pytest.approx(LARGE_SD)


def test_pulse_fit_windows_grow_from_the_input_onset():
    t = np.arange(1, 101) * 1e-3  # frames 1..100 ms
    t_in = np.linspace(0, 0.1, 1001)
    u_in = np.where(t_in > 0.02, 1e-3 * np.sin(np.pi * np.clip(t_in - 0.02, 0, 0.03) / 0.03), 0)
    n = window_frames(t, t_in, u_in)
    assert n[-1] == t.size and n == sorted(set(n))
    onset = 0.02
    for k, f in zip(n[:-1], WINDOWS):  # window k ends `f` of the way from onset to the end
        assert t[k - 1] <= onset + f * (t[-1] - onset) < t[k]


def test_damping_as_a_ratio_or_as_two_coefficients_not_both(tmp_path):
    with pytest.raises(CalibrationError, match="either damping_ratio"):
        fit_oscillation(np.arange(60) / 960, np.zeros(60), ("damping_ratio", "damping_u"))


def test_two_way_clusters_see_an_error_shared_by_all_groups_at_one_time():
    """100 units x 100 frames; an error common to every unit in each 10-frame block (as the
    measured input's error reaches every unit at once): clustering by unit alone misses it,
    two-way clustering (unit, time block) recovers the spread of the slope over repeats."""
    rng = np.random.default_rng(5)
    unit, frame = np.meshgrid(np.arange(100), np.arange(100))
    unit, frame = unit.ravel(), frame.ravel()
    x = np.sin(frame / 7.0) * (1 + 0.2 * rng.normal(size=100))[unit]
    J = np.c_[x, np.ones_like(x)]
    slopes, sd_unit, sd_two = [], [], []
    for _ in range(40):
        shared = rng.normal(0, 0.05, 10)[frame // 10] * np.sin(frame / 7.0)
        y = 2.0 * x + shared + rng.normal(0, 0.05, x.size)
        coef = np.linalg.lstsq(J, y, rcond=None)[0]
        r = J @ coef - y
        slopes.append(coef[0])
        sd_unit.append(np.sqrt(covariance(J, r, unit)[0][0, 0]))
        sd_two.append(np.sqrt(covariance(J, r, (unit, frame // 10))[0][0, 0]))
    actual = np.std(slopes)
    assert np.median(sd_unit) < 0.5 * actual
    assert 0.6 * actual < np.median(sd_two) < 1.6 * actual
