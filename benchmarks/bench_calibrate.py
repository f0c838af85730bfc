"""Calibration benchmark: recovery of 20 %-perturbed material constants, stderr coverage, wall time.

- hinge: 3 tests x 3 runs x 200 points, force noise 0.02 N (`FORCE_NOISE_N`), several seeds;
- free oscillation: 600 frames at 960 fps, rotation noise 1e-3 rad, several seeds;
- pulse: one simulated 24x16 focusing experiment (2 mm raised-cosine pulse at 30 Hz, 1 kHz
  frames for 70 ms; truth by the rig's physics, Dopri8 with contact), tracked-position noise
  1.2e-5 m (0.02 px at 6e-4 m/px), fitted from the nominal material;
- rig: the whole chain on the simulated rig (`bench_rig`): `metarig rig` of a 24x16 sample with
  camera noise, DIC tracking, `metarig calibrate` from a start 20 % off;
- rig-precompressed (not in the default parts): the default experiment, pre-compressed, with a
  20 %-perturbed specimen, calibrated from the nominal material (`bench_rig_precompressed`).
Writes benchmarks/results/bench_calibrate.json (the parts run replace theirs). Run:
.venv/bin/python benchmarks/bench_calibrate.py [hinge] [oscillation] [pulse] [rig] [rig-precompressed]
"""

import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from design_engine.calibration.fit import start_damping_ratio, to_si
from design_engine.calibration.hinge import fit_hinge, hinge_sample, read_hinge_file
from design_engine.calibration.oscillation import fit_oscillation, log_decrement, oscillation_sample
from design_engine.calibration.pulse import fit_pulse
from design_engine.physics.material import reference_damping
from hardware_sim import characterisation as ch

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "results" / "bench_calibrate.json"


def summary(fit, truth_si):
    rows = {}
    for n in fit.names:
        if n not in truth_si:
            continue
        t, v, s = truth_si[n], fit.values[n], fit.stderr[n]
        rows[n] = {"truth": t, "value": v, "stderr": s, "rel_error": v / t - 1,
                   "rel_stderr": s / t, "z": (v - t) / s if s > 0 else None,
                   "undetermined": n in fit.undetermined}
    return rows


def si(m, n):
    return to_si(n, float(getattr(m, n)))


def bench_hinge(seeds):
    import tempfile

    f = {"k_stretch": 1.2, "k_shear": 0.8, "k_bend": 1.2}
    true = hinge_sample().material.scaled(f)
    out = []
    for seed in seeds:
        d = tempfile.mkdtemp()
        paths = ch.hinge_tests(true, d, runs=3, seed=100 * seed)
        t0 = time.perf_counter()
        fit = fit_hinge([read_hinge_file(p) for p in paths])
        out.append({"seed": seed, "wall_s": time.perf_counter() - t0, "rms_N": fit.rms,
                    "parameters": summary(fit, {n: si(true, n) for n in f})})
    return {"noise_N": ch.FORCE_NOISE_N, "points": "3 tests x 3 runs x 200", "factors": f,
            "runs": out}


def bench_oscillation(seeds):
    f = {"k_bend": 1.2, "damping_ratio": 0.8}  # a spec 6.3 truth: c_u, c_theta from zeta, k
    sample = oscillation_sample()
    m = sample.material
    zeta = 0.8 * start_damping_ratio(m, sample.lattice)
    true = m.scaled({"k_bend": 1.2})
    c_u, c_t = reference_damping(sample.lattice, zeta, true.density, true.k_shear, true.k_bend)
    true = true.replaced(damping_u=c_u, damping_theta=c_t)
    clean = ch.free_oscillation(true, ch.OscillationConfig(noise_rad=0.0, noise_m=0.0))
    modal = log_decrement(clean.t, clean.q[:, 1, 2])["damping_ratio"]
    out = []
    for seed in seeds:
        tr = ch.free_oscillation(true, ch.OscillationConfig(seed=seed))
        t0 = time.perf_counter()
        fit = fit_oscillation(tr.t, tr.q[:, 1, 2])
        ld = fit.extra["log_decrement"]
        out.append({"seed": seed, "wall_s": time.perf_counter() - t0, "rms_rad": fit.rms,
                    "parameters": summary(fit, {"damping_ratio": zeta, "k_bend": si(true, "k_bend")}),
                    "derived": {n: {"value": d["value"], "stderr": d["stderr"],
                                    "rel_error": d["value"] / si(true, n) - 1}
                                for n, d in fit.extra["derived"].items()},
                    "log_decrement": {"modal_damping_ratio": ld["damping_ratio"],
                                      "stderr": ld["stderr"], "noise_free": modal,
                                      "rel_error": ld["damping_ratio"] / modal - 1,
                                      "n_peaks": ld["n_peaks"]}})
    return {"noise_rad": ch.ROTATION_NOISE_RAD, "frames": 600, "fps": ch.FPS, "factors": f,
            "runs": out}


def bench_pulse(nx=24, ny=16, fit=("k_stretch", "k_shear", "k_bend", "damping_u", "damping_theta")):
    from hardware_sim import specimen as sp
    from hardware_sim.rig import MotionRecord, capture_times, specimen_motion

    fps = 1000.0
    t_in = np.arange(0.0, 0.08, 1e-4)
    u_in = 1e-3 * (1 - np.cos(2 * np.pi * 30 * np.clip(t_in - 0.005, 0, 1 / 30)))
    # recovery of known constants: the sample is its model (bench_discrepancy: one that is not)
    s = sp.build(sp.SpecimenConfig(scene="focusing-24x16", nx=nx, ny=ny, bias_angle_deg=25.0,
                                   imperfections=sp.NOMINAL))
    nominal = s.scene.material
    f = {"k_stretch": 1.2, "k_shear": 0.8, "k_bend": 1.2, "damping_u": 0.8, "damping_theta": 1.2}
    true = nominal.scaled(f)
    s = sp.Specimen(s.config, replace(s.scene, material=true), s.polygons_m, f)
    times = capture_times(0.001, 0.07, fps)
    t0 = time.perf_counter()
    q = specimen_motion(s, times, MotionRecord(t_in, u_in), None, fps).q[1:]
    truth_s = time.perf_counter() - t0
    noise = ch.POSITION_NOISE_M
    qn = q + np.random.default_rng(0).normal(0, noise, q.shape) * np.array([1.0, 1.0, 0.0])
    scene = replace(s.scene, material=nominal)
    t0 = time.perf_counter()
    fitted = fit_pulse(scene, times, qn, np.ones(q.shape[:2], bool), t_in, u_in, fit=fit)
    wall = time.perf_counter() - t0
    return {"lattice": [nx, ny], "frames": int(times.size), "fps": fps, "amplitude_m": 2e-3,
            "noise_m": noise, "factors": f, "truth_simulation_s": truth_s, "fit_wall_s": wall,
            "iterations": fitted.iterations, "rms_m": fitted.rms,
            "n_residuals": fitted.n, "solver": fitted.extra["config"],
            "parameters": summary(fitted, {n: si(true, n) for n in f})}


def calibrate_run(run: Path, cal: Path, truth: dict, flags: list[str]):
    """`metarig calibrate RUN --out CAL -q FLAGS...`: (its calibration.json, each fitted or
    derived constant that `truth` (SI) holds against it, wall s)."""
    import subprocess

    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "metarig", "calibrate", str(run), "--out", str(cal),
                    "-q", *flags], check=True, cwd=ROOT)
    wall = time.perf_counter() - t0
    doc = json.loads((cal / "calibration.json").read_text())
    derived = doc.get("derived", {})
    rows = {n: {"truth": truth[n], "value": p["value"], "stderr": p["stderr"],
                "rel_error": p["value"] / truth[n] - 1,
                "z": (p["value"] - truth[n]) / p["stderr"] if p["stderr"] else None,
                "derived": n in derived}
            for n, p in {**doc["parameters"], **derived}.items() if n in truth}
    return doc, rows, wall


def bench_rig(out=ROOT / "runs" / "bench-calibrate"):
    """The whole chain: `metarig rig` (24x16 periodic focusing sample, 7.5 mm pulse at 30 Hz,
    1000 fps, 1000x700 px at 0.4 mm/px, camera noise on; the true material is the default),
    tracked by DIC, then `metarig calibrate` of the run from a start 20 % off (k_shear x 1.2,
    k_bend x 0.8, damping ratio x 1.2), on the DIC poses and on the rig's ground-truth poses
    (the fit's own part of the error), and with k_stretch x 1.2 fitted as well."""
    import os
    import subprocess

    from design_engine.physics.material_file import default_si, save_material
    from ros_nodes.recorded_run import pulse_inputs

    run = out / "rig"
    rig_s = None  # the recording of an earlier run is reused: no rig time measured
    if not (run / "recording.mcap").exists():
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-m", "metarig", "rig", "--scene", "focusing-24x16",
                        "--strain", "0", "--width", "1000", "--height", "700", "--m-per-px",
                        "4e-4", "--specimen-level", "0", "--out", str(run)], check=True,
                       cwd=ROOT)
        rig_s = time.perf_counter() - t0
    d = default_si()
    scene = pulse_inputs(run, "truth")[0]
    truth = {n: to_si(n, float(getattr(scene.material, n)))
             for n in ("k_stretch", "k_shear", "k_bend", "damping_u", "damping_theta")}
    truth["damping_ratio"] = d["damping_ratio"]
    res = {"rig_s": rig_s, "load_before": os.getloadavg()}
    # (poses, perturbed start, --fit): the default fit with k_stretch known (from the hinge
    # tension test), then k_stretch 20 % off as well and fitted
    cases = {"dic": ("dic", {"k_shear": 1.2, "k_bend": 0.8, "damping_ratio": 1.2}, None),
             "truth": ("truth", {"k_shear": 1.2, "k_bend": 0.8, "damping_ratio": 1.2}, None),
             "dic_with_k_stretch": ("dic", {"k_stretch": 1.2, "k_shear": 1.2, "k_bend": 0.8,
                                            "damping_ratio": 1.2},
                                    "k_stretch,k_shear,k_bend,damping_ratio")}
    for name, (poses, factors, fit) in cases.items():
        start = out / f"start-{name}.toml"
        save_material(start, {k: d[k] * f for k, f in factors.items()}, None,
                      "bench_calibrate: the default material, 20 % off")
        doc, rows, wall = calibrate_run(run, out / f"cal-{name}", truth,
                                        ["--material", str(start), "--poses", poses,
                                         *(["--fit", fit] if fit else [])])
        res[name] = {"poses": poses, "start_factors": factors, "wall_s": wall,
                     "residual_m": doc["residual"], "n_residuals": doc["n_residuals"],
                     "iterations": doc["iterations"], "windows_frames": doc.get("windows_frames"),
                     "parameters": rows}
    res["load_after"] = os.getloadavg()
    return res


def bench_rig_precompressed(out=ROOT / "runs" / "bench-calibrate", perturb=0.2, seed=11):
    """The default experiment, pre-compressed (`metarig rig --perturb 0.2 --seed 11`: the
    24x16 sample at 2 %, defaults otherwise), then `metarig calibrate` of the run from the
    nominal material (the default fit), on the frames tracked now (`--poses track`) and on the
    rig's ground truth (`--poses truth`: the fit's own part of the error). Twice: with the
    specimen its model (`--specimen-level 0`; its true constants the nominal ones times the
    run's perturbation factors) and with the default imperfections (its truth the specimen's
    effective material, `Specimen.effective_si`: what a uniform model should find, to within
    the model error the imperfections make)."""
    import os
    import subprocess

    from hardware_sim.specimen import NOMINAL, Imperfections, SpecimenConfig, build
    from ros_nodes.logic.sequence import ExperimentPlan

    plan = ExperimentPlan()
    res = {"command": f"metarig rig --perturb {perturb} --seed {seed} [--specimen-level 0]; "
                      "metarig calibrate RUN --poses track|truth",
           "strain": plan.strain, "load_before": os.getloadavg()}
    for name, flags, imp in (("model", ["--specimen-level", "0"], NOMINAL),
                             ("imperfect", [], Imperfections())):
        run = out / f"rig-precompressed-{name}"
        rig_s = None  # the recording of an earlier run is reused: no rig time measured
        if not (run / "recording.mcap").exists():
            t0 = time.perf_counter()
            subprocess.run([sys.executable, "-m", "metarig", "rig", "--perturb", str(perturb),
                            "--seed", str(seed), *flags, "--no-compare", "--out", str(run)],
                           check=True, cwd=ROOT)
            rig_s = time.perf_counter() - t0
        specimen = build(SpecimenConfig(scene=plan.scene, nx=plan.nx, ny=plan.ny,
                                        perturb=perturb, seed=seed, imperfections=imp))
        truth = specimen.effective_si()
        part = {"rig_s": rig_s, "true_parameter_factors": specimen.factors}
        for poses in ("track", "truth"):
            cal = out / f"cal-precompressed-{name}-{poses}"
            doc, rows, wall = calibrate_run(run, cal, truth, ["--poses", poses])
            part[poses] = {"wall_s": wall, "residual_m": doc["residual"],
                           "weighted_by_pose_sigma": doc.get("weighted_by_pose_sigma"),
                           "parameters": rows}
            print(f"{name:9s} {poses:5s}: " + ", ".join(
                f"{n} {100 * r['rel_error']:+.2f} %" for n, r in rows.items()), flush=True)
        res[name] = part
    res["load_after"] = os.getloadavg()
    return res


def main(argv):
    res = {}
    parts = argv or ["hinge", "oscillation", "pulse", "rig"]
    if "hinge" in parts:
        res["hinge"] = bench_hinge([0, 1, 2, 3])
        print(json.dumps(res["hinge"], indent=1)[:3000], flush=True)
    if "oscillation" in parts:
        res["oscillation"] = bench_oscillation([0, 1, 2])
        print(json.dumps(res["oscillation"], indent=1)[:3000], flush=True)
    if "pulse" in parts:
        res["pulse_24x16"] = bench_pulse()
        print(json.dumps(res["pulse_24x16"], indent=1), flush=True)
    if "rig" in parts:
        res["rig_24x16"] = bench_rig()
        print(json.dumps(res["rig_24x16"], indent=1), flush=True)
    if "rig-precompressed" in parts:
        res["rig_precompressed_24x16"] = bench_rig_precompressed()
        print(json.dumps(res["rig_precompressed_24x16"], indent=1), flush=True)
    old = json.loads(OUT.read_text()) if OUT.exists() else {}
    old.update(res)
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(json.dumps(old, indent=1) + "\n")


if __name__ == "__main__":
    main(sys.argv[1:])
