"""Optimisation-level accuracy of the contact configurations (issue 12, item 4).

The focus-vs-protect task (24x18, 1 % and 8 % pre-compression, weights 0.75 / -0.25) run for
`--evals` evaluations from the same periodic start with each configuration:

- `default`: the automatic policy on the default model (static pre-compression);
- `dopri8-static`: adaptive Dopri8 at the reference tolerances with contact, static model;
- `baseline`: the reference configuration (Dopri5 at the spec tolerances, backsolve adjoint,
  float64) on the reference model (the dynamic pre-compression ramp).

Each run's best feasible design is then re-evaluated with the reference model (dynamic ramp,
Dopri8 at the reference tolerances) and with the static model (same solver): that "true"
objective is charted against the run's wall time. Runs live in OUT/<label>/ and resume when the
script is re-run (`metarig design` run folders). Writes OUT/bench_design_contact.json and .png
and copies both to benchmarks/results/.

    .venv/bin/python benchmarks/bench_design_contact.py [--evals 20] [--runs default,baseline]
"""

import argparse
import json
import os
import platform
import shutil
from pathlib import Path

HERE = Path(__file__).resolve().parent
RUNS = ("default", "dopri8-static", "baseline")


def _task_file(out: Path, precompression: str) -> Path:
    from design_engine.design.task import preset_path

    text = preset_path("focus-vs-protect").read_text()
    path = out / f"focus-vs-protect-{precompression}.toml"
    path.write_text(text.replace('precompression = "static"',
                                 f'precompression = "{precompression}"'))
    return path


def _true_objective(task_file: Path, x_mm, config) -> dict:
    """Scalarised objective (SI, as history.json) and its terms for design x with `config`."""
    from design_engine.design.evaluator import TaskEvaluator
    from design_engine.design.task import load_task

    task = load_task(task_file)
    ev = TaskEvaluator(task, config=config).evaluate(x_mm)
    return {"objective": task.scalarised_si(ev.terms), "terms": task.objectives_si(ev.terms)}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--evals", type=int, default=20)
    p.add_argument("--runs", default=",".join(RUNS))
    p.add_argument("--out", type=Path, default=Path("runs/bench-design-contact"))
    args = p.parse_args(argv)
    labels = [r for r in args.runs.split(",") if r]
    unknown = set(labels) - set(RUNS)
    if unknown:
        raise SystemExit(f"unknown runs {sorted(unknown)}; choose from {RUNS}")

    import numpy as np

    from design_engine.design.evaluator import TaskEvaluator
    from design_engine.design.optimize import resumable, run_design
    from design_engine.design.task import load_task
    from design_engine.solve.policy import contact_config
    from design_engine.studies.methods import baseline_method

    args.out.mkdir(parents=True, exist_ok=True)
    files = {m: _task_file(args.out, m) for m in ("static", "ramp")}
    report_path = args.out / "bench_design_contact.json"
    report = json.loads(report_path.read_text()) if report_path.exists() else {"runs": {}}
    report.update(evals=args.evals, machine={"platform": platform.platform(),
                                             "cpus": os.cpu_count(),
                                             "load_before": os.getloadavg()})
    setups = {"default": ("static", None), "dopri8-static": ("static", contact_config()),
              "baseline": ("ramp", baseline_method().config)}
    for label in labels:
        model, config = setups[label]
        task = load_task(files[model], max_evals=args.evals)
        folder = args.out / label
        print(f"{label}: {args.evals} evaluations ({model} pre-compression) ...", flush=True)
        run = run_design(task, folder, resume=resumable(folder), progress=True,
                         evaluator=TaskEvaluator(task, config=config))
        history = run.evaluations
        wall = float(sum(r["wall_s"] for r in history))
        best = run.best if run.best is not None else len(history) - 1
        x = run.best_x if run.best_x is not None else run.last_x
        print(f"{label}: re-evaluating the best design (evaluation {best + 1}) ...", flush=True)
        report["runs"][label] = {
            "model": model, "status": run.status, "evaluations": len(history),
            "wall_s": wall, "sim_s": float(sum(r["sim_s"] for r in history)),
            "best_eval": best + 1, "own_objective": history[best]["objective"],
            "history": [[float(np.sum([h["wall_s"] for h in history[:k + 1]])), h["objective"]]
                        for k, h in enumerate(history)],
            "true_ramp": _true_objective(files["ramp"], x, contact_config()),
            "true_static": _true_objective(files["static"], x, contact_config()),
        }
        report_path.write_text(json.dumps(report, indent=2))
    report["machine"]["load_after"] = os.getloadavg()
    report_path.write_text(json.dumps(report, indent=2))
    _plot(report, args.out / "bench_design_contact.png")
    for name in ("bench_design_contact.json", "bench_design_contact.png"):
        shutil.copy(args.out / name, HERE / "results" / name)
    for label, r in report["runs"].items():
        print(f"{label:<14} {r['wall_s']:8.0f} s  own {r['own_objective']:.4e}  true (ramp) "
              f"{r['true_ramp']['objective']:.4e}  true (static) "
              f"{r['true_static']['objective']:.4e}")
    return 0


def _plot(report: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for label, r in report["runs"].items():
        h = [(t, v) for t, v in r["history"] if v is not None]
        line, = ax.plot([t for t, _ in h], [v * 1e3 for _, v in h], lw=1, alpha=0.6,
                        label=f"{label}: own objective")
        ax.plot([r["wall_s"]], [r["true_ramp"]["objective"] * 1e3], "o", color=line.get_color(),
                label=f"{label}: best design, reference model (ramp)")
        ax.plot([r["wall_s"]], [r["true_static"]["objective"] * 1e3], "s", mfc="none",
                color=line.get_color(), label=f"{label}: best design, static model")
    ax.set_xscale("log")
    ax.set_xlabel("wall time of the run, s (2 cores)")
    ax.set_ylabel("0.75 J(1 %) - 0.25 J(8 %), mJ")
    ax.set_title(f"focus-vs-protect 24x18, {report['evals']} evaluations, same start")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


if __name__ == "__main__":
    raise SystemExit(main())
