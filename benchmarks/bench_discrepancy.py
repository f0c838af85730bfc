"""A specimen that is not its model: comparison error against the discrepancy level, and what the
calibration makes of a discrepant specimen.

- comparison: the simulated rig's specimen with every imperfection scaled by a level (0, 0.5,
  1, 2 x the defaults of `hardware_sim.specimen.Imperfections`, one seeded draw), its true
  motion at 1 kHz (the rig's physics) compared with the nominal model's simulation of the same
  measured input (`comparison.experiment.compare_experiment` on the rig's ground-truth poses:
  the specimen's part of the error, without the tracker's); on the optimised 24x16 focusing
  design (`benchmarks/results/design_focusing-24x16.json`) under the paper's pulse (7.5 mm,
  30 Hz), and on the default `metarig rig` sample (the periodic 24x16 lattice, 2 % pre-
  compression). At level 1 each imperfection alone as well.
- calibration: `design_engine.calibration.calibrate.fit_pulse` (k_shear, k_bend, damping ratio) on a small
  discrepant specimen (8x6, the asymmetric design of tests/test_specimen.py, 4 mm pulse,
  tracked-position noise 1.2e-5 m), at levels 0 and 1: the fitted values, their stated errors
  (statistical and model parts) and the effective truth, the nominal material with the
  thickness law and the mean of the per-ligament factors applied.

Writes `bench_discrepancy.json` and `bench_discrepancy.png` into --out (default
benchmarks/results), with the machine and its load.

    .venv/bin/python benchmarks/bench_discrepancy.py [--parts comparison,calibration] [--out DIR]
"""

import argparse
import json
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "tests"))

from discrepant import asymmetric_design, raised_cosine  # noqa: E402
from machine import describe  # noqa: E402

LEVELS = (0.0, 0.5, 1.0, 2.0)
FPS = 1000.0
METRICS = ("velocity_nrmse", "energy_map_correlation", "target_peak_ke_rel_err")


def stage_record(strain: float, height_m: float, t_end_s: float):
    """Stage closing at 0.25 strain/s to `strain`, then held (the rig's protocol)."""
    t = np.arange(0.0, t_end_s, 1e-3)
    return t, np.minimum(0.25 * height_m * t, strain * height_m)


def comparison_case(cfg, levels, t_in, u_in, times, stage=None, each=True):
    """Comparison metrics of the specimen `cfg` at each level (and each imperfection alone);
    `stage` = (t s, closing m, closing speed m/s, hold time s) or None."""
    from comparison.experiment import compare_experiment, scene_of_design
    from design_engine.solve.policy import contact_config
    from hardware_sim import specimen as sp
    from hardware_sim.rig import MotionRecord, specimen_motion
    from metarig.trajectory import Trajectory

    nominal = sp.build(replace(cfg, imperfections=sp.NOMINAL))
    scene = scene_of_design(json.loads(nominal.design_json()))
    stage_rec = None if stage is None else MotionRecord(*stage[:2])

    def one(imp):
        t0 = time.perf_counter()
        s = sp.build(replace(cfg, imperfections=imp))
        traj = specimen_motion(s, times, MotionRecord(t_in, u_in), stage_rec, FPS)
        poses = Trajectory.from_positions(times - times[0], traj.q[1:])
        ec = compare_experiment(scene, poses, times[0], t_in, u_in,
                                *(stage if stage is not None else (None,) * 4),
                                config=contact_config())
        m = ec.comparison.metrics
        out = {k: float(m[k]) for k in METRICS}
        out["wall_s"] = time.perf_counter() - t0
        print(imp, out, flush=True)
        return out

    res = {"levels": {str(lv): one(sp.Imperfections(level=lv)) for lv in levels}}
    if each:
        off = {n: 0.0 for n in ("tolerance_m", "ligament_scatter", "damping_scatter",
                                "thickness_error", "friction_hz")}
        res["each_alone_at_level_1"] = {
            n: one(sp.Imperfections(**{**off, n: getattr(sp.Imperfections(), n)})) for n in off}
    return res


def bench_comparison(design: str, quick: bool):
    from hardware_sim import specimen as sp
    from hardware_sim.rig import capture_times

    t_in, u_in = raised_cosine(7.5e-3, 0.09)
    times = capture_times(0.001, 0.075, FPS)
    out = {"focusing_24x16_optimised": {
        "design": design, "pulse": "7.5 mm, 30 Hz", "frames": int(times.size),
        **comparison_case(sp.SpecimenConfig(scene="focusing-24x16", design_path=design),
                          LEVELS, t_in, u_in, times, each=not quick)}}
    if quick:
        return out
    # the default experiment's sample: periodic 24x16 lattice, 2 % pre-compression by the
    # stages (closing from rest, then held), the pulse 20 ms after the stages hold
    strain, height = 0.02, 15 * 0.015
    t_hold = strain / 0.25
    t0 = t_hold + 0.02
    t_in2 = np.arange(0.0, t0 + 0.09, 1e-4)  # the pulse 5 ms after t0
    u_in2 = np.interp(t_in2 - t0, *raised_cosine(7.5e-3, 0.09), left=0.0)
    times2 = capture_times(t0, t0 + 0.075, FPS)
    cfg = sp.SpecimenConfig()  # precompression-24x18 resized to 24x16, as `metarig rig`
    out["precompression_24x16_periodic"] = {
        "design": "periodic, 25 deg", "strain": strain, "pulse": "7.5 mm, 30 Hz",
        "frames": int(times2.size),
        **comparison_case(cfg, LEVELS, t_in2, u_in2, times2,
                          stage=(*stage_record(strain, height, t0 + 0.09), 0.25 * height,
                                 t_hold), each=False)}
    return out


def bench_calibration(levels=(0.0, 1.0), seed: int = 0):
    import tempfile

    from design_engine.calibration.pulse import fit_pulse
    from design_engine.physics.material import default_si
    from hardware_sim import characterisation as ch
    from hardware_sim import specimen as sp
    from hardware_sim.rig import MotionRecord, capture_times, specimen_motion

    design = asymmetric_design(Path(tempfile.mkdtemp()) / "design.json")
    cfg = sp.SpecimenConfig(scene="focusing-24x16", design_path=str(design), seed=3)
    nominal = sp.build(replace(cfg, imperfections=sp.NOMINAL))
    t_in, u_in = raised_cosine(4e-3, 0.08)
    times = capture_times(0.001, 0.07, FPS)
    fit_names = ("k_shear", "k_bend", "damping_ratio")
    start = nominal.scene.material.scaled({"k_shear": 1.2, "k_bend": 0.8})
    out = {"scene": "focusing 8x6, asymmetric design (seed 7)", "pulse": "4 mm, 30 Hz",
           "noise_m": ch.POSITION_NOISE_M, "start_factors": {"k_shear": 1.2, "k_bend": 0.8},
           "levels": {}}
    for level in levels:
        s = sp.build(replace(cfg, imperfections=sp.Imperfections(level=level)))
        q = specimen_motion(s, times, MotionRecord(t_in, u_in), None, FPS).q[1:]
        q = q + np.random.default_rng(seed).normal(0, ch.POSITION_NOISE_M, q.shape) * [1, 1, 0]
        t0 = time.perf_counter()
        fit = fit_pulse(nominal.scene, times, q, np.ones(q.shape[:2], bool), t_in, u_in,
                            fit=fit_names, start=start)
        eff = s.effective_si()
        # the effective truth: the specimen's mean material (the damping ratio: the nominal one,
        # which scatter is around; the friction adds 4 % to the damping on top)
        truth = {"k_shear": eff["k_shear"], "k_bend": eff["k_bend"],
                 "damping_ratio": default_si()["damping_ratio"]}
        me = fit.extra["model_error"]
        rows = {}
        for n in fit_names:
            v, e, t = fit.values[n], fit.stderr[n], truth[n]
            rows[n] = {"effective_truth": t, "value": v, "stderr": e,
                       "stderr_statistical": fit.extra["stderr_statistical"][n],
                       "stderr_model": me["stderr_model"][n], "rel_error": v / t - 1,
                       "z_statistical": (v - t) / fit.extra["stderr_statistical"][n],
                       "rel_stderr": e / t, "z": (v - t) / e, "covered_3_stderr":
                       bool(abs(v - t) < 3 * e)}
        out["levels"][str(level)] = {
            "parameters": rows, "residual_rms_m": fit.rms,
            "model_error": {k: v for k, v in me.items() if k != "stderr_model"},
            "wall_s": time.perf_counter() - t0}
        print(level, json.dumps(out["levels"][str(level)], indent=1), flush=True)
    return out


def plot(res, path: Path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cases = [(k, v) for k, v in res.get("comparison", {}).items()
             if isinstance(v, dict) and "levels" in v]
    cal = res.get("calibration")
    fig, axes = plt.subplots(1, 3, figsize=(14, 4))
    for name, c in cases:
        lv = sorted(float(x) for x in c["levels"])
        get = [c["levels"][str(x)] for x in lv]
        axes[0].plot(lv, [g["velocity_nrmse"] for g in get], "o-", label=name)
        axes[0].plot(lv, [abs(g["target_peak_ke_rel_err"]) for g in get], "s--",
                     label=f"{name}: |target peak KE error|")
        axes[1].semilogy(lv, [max(1 - g["energy_map_correlation"], 1e-9) for g in get], "o-",
                         label=name)
    axes[0].axhline(0.05, color="grey", lw=0.8, ls=":")
    axes[0].text(0.02, 0.055, "focusing, measured target peak ~5 % off (paper)", fontsize=7,
                 color="grey")
    axes[0].set(xlabel="discrepancy level (x defaults)", ylabel="velocity NRMSE, |rel. error|",
                title="comparison error (ground-truth poses)")
    axes[0].legend(fontsize=7)
    axes[1].set(xlabel="discrepancy level (x defaults)", ylabel="1 - energy-map correlation",
                title="energy-map correlation")
    axes[1].legend(fontsize=7)
    if cal:
        names = ("k_shear", "k_bend", "damping_ratio")
        for j, (level, r) in enumerate(sorted(cal["levels"].items())):
            x = np.arange(len(names)) + 0.25 * (j - 0.5)
            axes[2].plot(x, [r["parameters"][n]["z"] for n in names], "o", color=f"C{j}",
                         label=f"level {float(level):g}: stated stderr (statistical + model)")
            axes[2].plot(x, [r["parameters"][n]["z_statistical"] for n in names], "x",
                         color=f"C{j}", label=f"level {float(level):g}: statistical alone")
        for y in (-3, 3):
            axes[2].axhline(y, color="grey", lw=0.8, ls=":")
        axes[2].axhline(0, color="k", lw=0.8)
        axes[2].set_xticks(range(len(names)), names)
        axes[2].set(ylabel="(fit - effective truth) / stderr",
                    title="calibration on a discrepant 8x6 specimen")
        axes[2].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--parts", default="comparison,calibration",
                   help="comma-separated: comparison, calibration (none: redraw the chart)")
    p.add_argument("--design", default=str(ROOT / "benchmarks/results/design_focusing-24x16.json"),
                   help="the optimised focusing design")
    p.add_argument("--quick", action="store_true",
                   help="comparison: only the focusing design, no imperfection alone")
    p.add_argument("--out", type=Path, default=ROOT / "benchmarks/results")
    args = p.parse_args(argv)
    parts = set(args.parts.split(","))
    path = args.out / "bench_discrepancy.json"
    if parts == {"none"}:
        plot(json.loads(path.read_text()), args.out / "bench_discrepancy.png")
        return 0
    from hardware_sim.specimen import Imperfections

    res = {"defaults": {k: getattr(Imperfections(), k) for k in Imperfections.__slots__}}
    for part, run in (("comparison", lambda: bench_comparison(args.design, args.quick)),
                      ("calibration", bench_calibration)):
        if part in parts:
            load, t0 = os.getloadavg(), time.perf_counter()
            res[part] = run()
            res[part].update(machine=describe(), load_before=load, load_after=os.getloadavg(),
                             wall_s=time.perf_counter() - t0)
    args.out.mkdir(parents=True, exist_ok=True)
    old = json.loads(path.read_text()) if path.exists() else {}
    old.update(res)
    path.write_text(json.dumps(old, indent=1) + "\n")
    plot(old, args.out / "bench_discrepancy.png")
    print(f"wrote {path}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
