"""`metarig demo [--out runs/demo]`: the whole product once, on its built-in default.

1. a short design optimisation on a small lattice (task `focusing-demo`: 8x6 units, 2 mm pulse,
   8 evaluations) -> `DIR/design/` (design.json, history, plots) and `DIR/design.svg`;
2. a simulated experiment of that design through the ROS nodes (`metarig rig --design`), its
   frames tracked and compared with the simulation -> `DIR/recording.mcap`, `comparison.rrd`,
   `summary.json`, the PNG plots;
3. a short report: where everything is, the objective before and after, the comparison errors,
   every step's wall time, how to open the `.rrd` and the MCAP (also as `DIR/demo.json`).
"""

import argparse
import json
import logging
import subprocess
import sys
import time
from pathlib import Path

DEMO_TASK = "focusing-demo"
# The sample is its model (`--specimen-level 0`): the demo's 8x6 design, eight small MMA steps
# from the symmetric periodic lattice, still responds on that lattice's bifurcation, which the
# default imperfections of a fabricated sample tip onto another branch (velocity NRMSE 1.1
# against the nominal model instead of 0.06); the imperfect specimen's comparison and
# calibration are tests/test_specimen.py and benchmarks/bench_discrepancy.py.
RIG_ARGS = ["--scene", "focusing-24x16", "--strain", "0", "--amplitude", "0.002",
            "--width", "480", "--height", "360", "--m-per-px", "3e-4", "--record-s", "0.08",
            "--specimen-level", "0"]

log = logging.getLogger("metarig.demo")


class DemoError(RuntimeError):
    """A step of the demo failed (the message names it)."""


def _step(name: str, timings: dict, argv: list[str]) -> None:
    """Run `metarig ARGV` as its own process (the command a user would type; its progress and
    messages go straight to this terminal) and time it."""
    print(f"[demo] {name} ...", flush=True)
    t0 = time.perf_counter()
    code = subprocess.run([sys.executable, "-m", "metarig", *argv]).returncode
    timings[name] = round(time.perf_counter() - t0, 1)
    if code != 0:
        raise DemoError(f"{name} failed (exit code {code}); see the messages above")
    print(f"[demo] {name}: done in {timings[name]:.1f} s", flush=True)


def run_demo(out: Path) -> dict:
    """Run the three steps into `out` and return the report (see the module docstring)."""
    out.mkdir(parents=True, exist_ok=True)
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    again = ["--resume"] if (out / "design" / "run.json").exists() else []  # a re-run: resume
    _step("design", timings,
          ["design", DEMO_TASK, "--out", str(out / "design"), "--quiet", *again])
    design = out / "design" / "design.json"  # the rig writes the sample's as DIR/design.json
    if not design.exists():
        raise DemoError("design: no feasible design was found")
    _step("export", timings, ["export", str(design), "--svg", str(out / "design.svg")])
    _step("rig", timings,
          ["rig", "--design", str(design), *RIG_ARGS, "--out", str(out)])
    history = json.loads((out / "design" / "history.json").read_text())["evaluations"]
    best = json.loads(design.read_text())
    summary = json.loads((out / "summary.json").read_text())
    run = json.loads((out / "run.json").read_text())
    timings["of which tracking and comparison"] = round(run["timings_s"]["track_and_compare"], 1)
    timings["total"] = round(time.perf_counter() - t0, 1)
    report = {
        "run_folder": str(out),
        "design": {"task": DEMO_TASK, "evaluations": len(history),
                   "objective_before_J": history[0]["objective"],
                   "objective_after_J": best["objective"], "best_evaluation": best["eval"]},
        "comparison": {k: summary[k] for k in (
            "velocity_nrmse", "energy_map_correlation", "target_peak_ke_rel_err",
            "max_displacement_error_m", "lost_units", "onset_s")},
        "files": {"design": str(design), "svg": str(out / "design.svg"),
                  "mcap": summary["mcap"], "rrd": summary["rrd"],
                  "summary": str(out / "summary.json")},
        "timings_s": timings,
    }
    (out / "demo.json").write_text(json.dumps(report, indent=2))
    return report


def print_report(r: dict) -> None:
    d, c, f, t = r["design"], r["comparison"], r["files"], r["timings_s"]
    ratio = d["objective_after_J"] / d["objective_before_J"] if d["objective_before_J"] else 0
    print(f"""
metarig demo: done in {t['total']:.0f} s -> {r['run_folder']}
  design     {d['task']}, {d['evaluations']} evaluations: target energy {d['objective_before_J']:.3g} J
             -> {d['objective_after_J']:.3g} J (x{ratio:.1f}, evaluation {d['best_evaluation']})
             {f['design']}, {f['svg']}
  experiment the design on the simulated rig (ROS nodes), its frames tracked by DIC and
             compared with the simulation of the measured input:
             velocity NRMSE {c['velocity_nrmse']:.1%}, target peak kinetic energy \
{c['target_peak_ke_rel_err']:+.1%},
             energy-map correlation {c['energy_map_correlation']:.4f}, max displacement error \
{c['max_displacement_error_m'] * 1e3:.3f} mm,
             {c['lost_units']} lost units
  time       """ + ", ".join(f"{k} {v:.1f} s" for k, v in t.items() if k != "total") + f"""
  look       rerun {f['rrd']}      (experiment and simulation side by side)
             rerun {f['mcap']}     (the raw recording)
             {f['summary']}, {r['run_folder']}/*.png
""")


def demo_main(argv: list[str] | None = None) -> int:
    """Design a small focusing lattice, test it on the simulated rig, track, compare, report."""
    p = argparse.ArgumentParser(prog="metarig demo", description=demo_main.__doc__,
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--out", type=Path, default=Path("runs/demo"), help="run folder")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    try:
        report = run_demo(args.out)
    except DemoError as exc:
        print(f"metarig demo: error: {exc}", file=sys.stderr)
        return 1
    print_report(report)
    return 0
