"""Optimisation-level accuracy of the contact configurations (issues 12 and 26).

A task run for `--evals` evaluations from the same start with each configuration:

- `default`: the automatic policy on the default model (static pre-compression), its solves
  on every core this process may use (`TaskEvaluator(threads=None)`);
- `default-1thread`: the same on one thread, as a Dask worker of a sweep runs it;
- `dopri8-static`: adaptive Dopri8 at the reference tolerances with contact, static model;
- `baseline`: the reference configuration (Dopri5 at the spec tolerances, backsolve adjoint,
  float64) on the reference model (the dynamic pre-compression ramp where the task has one).

`--task focus-vs-protect` (the default: 24x18, 1 % and 8 % pre-compression, weights 0.75 /
-0.25): each run's best feasible design is re-evaluated with the reference model (dynamic ramp,
Dopri8 at the reference tolerances) and with the static model (same solver). `--task focusing`
(24x16, no pre-compression, so one model): re-evaluated with Dopri8 at the reference
tolerances. With `--recheck-at K ...` the best feasible design after evaluation K is also
re-evaluated so (`true_history`: [wall time after K, K, objective]): the "true" objective
against the run's wall time. Runs live in OUT/<label>/ and resume when the script is re-run
(`metarig design` run folders). Writes OUT/NAME.json and .png, NAME by default
bench_design_contact[_<task>] (no suffix for focus-vs-protect), and copies both to
benchmarks/results/ (`--name` keeps a new measurement from overwriting a committed one).

    .venv/bin/python benchmarks/bench_design_contact.py [--task focus-vs-protect|focusing]
        [--evals 20] [--runs default,baseline] [--recheck-at 10 20 40 60] [--cold] [--out DIR]
        [--seed N [--random-amplitude A]] [--name NAME]

`--cold`: each run in a process of its own with an empty compilation cache of its own, so that
its wall time includes what a fresh machine compiles.
"""

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
from pathlib import Path

from machine import cpu_model

HERE = Path(__file__).resolve().parent
RUNS = ("default", "default-1thread", "dopri8-static", "baseline")
TASKS = ("focus-vs-protect", "focusing")


def _task_file(out: Path, task: str, precompression: str, amplitude: float | None = None) -> Path:
    from design_engine.design.task import preset_path

    text = preset_path(task).read_text()
    if amplitude is not None:  # the seeded start's noise, a fraction of the spacing
        if "[initial]\n" not in text:
            raise SystemExit(f"the {task} preset has no [initial] section to set "
                             "random_amplitude in")
        text = text.replace("[initial]\n", f"[initial]\nrandom_amplitude = {amplitude!r}\n", 1)
    path = out / f"{task}-{precompression}.toml"
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
    p.add_argument("--task", default="focus-vs-protect", choices=TASKS)
    p.add_argument("--evals", type=int, default=20)
    p.add_argument("--runs", default=",".join(RUNS))
    p.add_argument("--recheck-at", type=int, nargs="*", default=[],
                   help="also re-evaluate the best feasible design after these evaluations")
    p.add_argument("--out", type=Path, help="default runs/bench-design-contact[-<task>]")
    p.add_argument("--cold", action="store_true",
                   help="each run in a process of its own, compiling into an empty cache of its "
                        "own (OUT/jax-cache-<run>), as on a fresh machine")
    p.add_argument("--seed", type=int, help="every run starts from the seeded random design of "
                                            "`metarig design --seed N` (default the task's start)")
    p.add_argument("--random-amplitude", type=float, help="with --seed: the start's noise as a "
                   "fraction of the spacing, replacing the task's (1e-6: the task's start moved "
                   "by nanometres)")
    p.add_argument("--name", help="the report's file name without its extension, in OUT and "
                                  "benchmarks/results/ (default bench_design_contact[_<task>])")
    args = p.parse_args(argv)
    if args.random_amplitude is not None and args.seed is None:
        p.error("--random-amplitude needs --seed")
    labels = [r for r in args.runs.split(",") if r]
    unknown = set(labels) - set(RUNS)
    if unknown:
        raise SystemExit(f"unknown runs {sorted(unknown)}; choose from {RUNS}")
    suffix = "" if args.task == "focus-vs-protect" else f"_{args.task}"
    args.out = args.out or Path("runs/bench-design-contact" + suffix.replace("_", "-"))
    name = args.name or f"bench_design_contact{suffix}"
    if args.cold:
        for label in labels:  # one after the other; each merges its run into the report
            cache = args.out / f"jax-cache-{label}"
            if not (args.out / label / "history.json").exists():
                shutil.rmtree(cache, ignore_errors=True)  # a resumed run keeps what it compiled
            # this run alone, with every other option as parsed here
            child = ["--task", args.task, "--evals", str(args.evals), "--runs", label,
                     "--out", str(args.out), "--name", name,
                     *(["--seed", str(args.seed)] if args.seed is not None else []),
                     *(["--random-amplitude", repr(args.random_amplitude)]
                       if args.random_amplitude is not None else []),
                     "--recheck-at", *map(str, args.recheck_at)]
            rc = subprocess.call([sys.executable, __file__, *child],
                                 env=dict(os.environ, METARIG_JAX_CACHE=str(cache.resolve())))
            if rc:
                return rc
        return 0

    import numpy as np

    from design_engine.design.evaluator import TaskEvaluator
    from design_engine.design.optimize import best_feasible, resumable, run_design
    from design_engine.design.task import load_task
    from design_engine.solve.policy import contact_config
    from design_engine.studies.methods import baseline_method

    args.out.mkdir(parents=True, exist_ok=True)
    # the reference model: the dynamic ramp where the task pre-compresses, else its one model
    ramps = args.task == "focus-vs-protect"
    files = {m: _task_file(args.out, args.task, m, args.random_amplitude)
             for m in ("static", "ramp")}
    if not ramps:
        files["ramp"] = files["static"]
    report_path = args.out / f"{name}.json"
    report = json.loads(report_path.read_text()) if report_path.exists() else {"runs": {}}
    report.update(task=args.task, evals=args.evals, seed=args.seed,
                  random_amplitude=args.random_amplitude, machine={
        "platform": platform.platform(), "cpu": cpu_model(), "cpus": os.cpu_count(),
        "load_before": os.getloadavg()})
    setups = {"default": ("static", None, None), "default-1thread": ("static", None, 1),
              "dopri8-static": ("static", contact_config(), None),
              "baseline": ("ramp", baseline_method().config, None)}
    for label in labels:
        model, config, threads = setups[label]
        task = load_task(files[model], max_evals=args.evals, seed=args.seed)
        folder = args.out / label
        print(f"{label}: {args.evals} evaluations"
              + (f" ({model} pre-compression)" if ramps else "") + " ...", flush=True)
        on_record = folder / "history.json"
        done = on_record.exists() and len(json.loads(on_record.read_text())["evaluations"]) \
            >= args.evals
        load = [os.getloadavg()[0]]
        run = run_design(task, folder, resume=resumable(folder), progress=True,
                         evaluator=TaskEvaluator(task, config=config, threads=threads))
        load.append(os.getloadavg()[0])
        if done:  # replayed from its record: the load of the invocation that ran it
            load = report["runs"].get(label, {}).get("load_1min", load)
        history = run.evaluations
        wall = float(sum(r["wall_s"] for r in history))
        best = run.best if run.best is not None else len(history) - 1
        x = run.best_x if run.best_x is not None else run.last_x
        print(f"{label}: re-evaluating the best design (evaluation {best + 1}) ...", flush=True)
        true_ramp = _true_objective(files["ramp"], x, contact_config())
        true_history = []
        xs = np.load(folder / "checkpoint.npz")["x"]
        for k in sorted({k for k in args.recheck_at if 0 < k <= len(history)}):
            b = best_feasible(history[:k], task.goal)
            if b is None:
                continue
            print(f"{label}: the best design after {k} evaluations ({b + 1}) ...", flush=True)
            true = true_ramp if b == best else _true_objective(  # the last: the best's, above
                files["ramp"], task.embed(xs[b]), contact_config())
            true_history.append([float(sum(h["wall_s"] for h in history[:k])), k, b + 1,
                                 true["objective"]])
        report["runs"][label] = {
            "model": model, "status": run.status, "evaluations": len(history),
            "wall_s": wall, "sim_s": float(sum(r["sim_s"] for r in history)),
            "best_eval": best + 1, "own_objective": history[best]["objective"],
            "history": [[float(np.sum([h["wall_s"] for h in history[:k + 1]])), h["objective"]]
                        for k, h in enumerate(history)],
            "true_ramp": true_ramp,
            "true_static": (_true_objective(files["static"], x, contact_config()) if ramps
                            else None),
            "true_history": true_history,
            "load_1min": load,  # 1-minute load average before and after its design run
        }
        report_path.write_text(json.dumps(report, indent=2))
    report["machine"]["load_after"] = os.getloadavg()
    report_path.write_text(json.dumps(report, indent=2))
    _plot(report, args.out / f"{name}.png")
    for file in (f"{name}.json", f"{name}.png"):
        shutil.copy(args.out / file, HERE / "results" / file)
    for label, r in report["runs"].items():
        static = r.get("true_static")
        print(f"{label:<14} {r['wall_s']:8.0f} s  own {r['own_objective']:.4e}  true "
              f"(reference model) {r['true_ramp']['objective']:.4e}"
              + (f"  true (static) {static['objective']:.4e}" if static else ""))
    return 0


def _plot(report: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    ramps = report.get("task", "focus-vs-protect") == "focus-vs-protect"
    reference = "reference model (ramp)" if ramps else "reference configuration (Dopri8)"
    for label, r in report["runs"].items():
        h = [(t, v) for t, v in r["history"] if v is not None]
        line, = ax.plot([t for t, _ in h], [v * 1e3 for _, v in h], lw=1, alpha=0.6,
                        label=f"{label}: own objective")
        true = r.get("true_history") or []
        if true:
            ax.plot([t for t, *_ in true], [v * 1e3 for *_, v in true], "o--",
                    color=line.get_color(), ms=4, lw=0.8,
                    label=f"{label}: best so far, {reference}")
        ax.plot([r["wall_s"]], [r["true_ramp"]["objective"] * 1e3], "o", color=line.get_color(),
                label=None if true else f"{label}: best design, {reference}")
        if r.get("true_static"):
            ax.plot([r["wall_s"]], [r["true_static"]["objective"] * 1e3], "s", mfc="none",
                    color=line.get_color(), label=f"{label}: best design, static model")
    ax.set_xscale("log")  # plain numbers at 1, 2 and 5 of each decade
    ax.xaxis.set_major_locator(matplotlib.ticker.LogLocator(subs=(1.0, 2.0, 5.0)))
    ax.xaxis.set_major_formatter(matplotlib.ticker.ScalarFormatter())
    ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax.set_xlabel("wall time of the run, s (2 cores)")
    if ramps:
        ax.set_ylabel("0.75 J(1 %) - 0.25 J(8 %), mJ")
        ax.set_title(f"focus-vs-protect 24x18, {report['evals']} evaluations, same start")
    else:
        ax.set_ylabel("objective (history.json), mJ")
        ax.set_title(f"{report['task']}, {report['evals']} evaluations, same start")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


if __name__ == "__main__":
    raise SystemExit(main())
