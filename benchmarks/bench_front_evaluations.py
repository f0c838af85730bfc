"""What a Pareto front's evaluations cost and how many fail (issue 26's front targets).

Runs (or resumes, or finds finished) a `metarig pareto` sweep with the given settings into
--out, then reads every run's `history.json` and reports: the evaluations, how many failed and
why (used up the step budget `budget.max_solve_steps`; any other reason, named), and the wall
time of an evaluation on a worker (median, 90th percentile, longest; the first evaluation of a
run, which compiles, apart), with how often each scene counted a Dopri8 solve and why
(`dopri8_why_per_scene`: after a work-energy drift, with the last drift the evaluation's event
reports for the scene; after the half-step check; otherwise), and the same times by how many of
its scenes an evaluation solved with Dopri8 (`eval_s_by_dopri8_scenes`; `"0, no event"`: no
Dopri8 and nothing re-solved, re-chosen or judged again). JSON in
OUT/NAME.json (--name, default bench_front_evaluations), copied to benchmarks/results/.

    .venv/bin/python benchmarks/bench_front_evaluations.py [--task focus-vs-protect]
        [--weights 0,0.2,0.4,0.6,0.8,1] [--starts 20,30] [--max-evals 12] [--workers 2]
        [--out runs/bench-front-evaluations] [--name NAME] [--report-only]

Ctrl-C stops the sweep and reports what its runs recorded so far (`"complete": false`);
running the same command again resumes it. `--report-only` reports the runs in --out without
running anything (`"complete"`: whether every run recorded its budget; the sweep's wall time
and load are those of the report already in --out, if any).
"""

import argparse
import json
import os
import platform
import re
import shutil
import time
from collections import Counter
from pathlib import Path

import numpy as np

from machine import cpu_model

HERE = Path(__file__).resolve().parent
BUDGET = "step budget"  # in the event of an evaluation that used up budget.max_solve_steps


def summarise(out: Path) -> dict:
    """The evaluations of every run of the sweep in `out`: counts, failures by reason, times."""
    evals, first, failed, reasons, dopri8 = [], [], 0, Counter(), Counter()
    classes: dict[str, list[float]] = {}  # how many scenes Dopri8 solved -> evaluation times
    why: dict[str, dict] = {}  # scene -> why its Dopri8 solves counted (the report's entry)
    budget = 0
    runs = sorted((out / "runs").glob("*/history.json"))
    if not runs:
        raise SystemExit(f"no design runs recorded in {out / 'runs'}")
    per_run = []
    for path in runs:
        history = json.loads(path.read_text())["evaluations"]
        per_run.append(len(history))
        for e in history:
            (first if e["eval"] == 1 else evals).append(float(e["wall_s"]))
            if e.get("failed"):
                failed += 1
                event = e.get("event") or ""
                if BUDGET in event:
                    budget += 1
                else:
                    reasons[event[:120]] += 1
            event = e.get("event") or ""
            solvers = [rec["config"]["solver"] for rec in (e.get("solver") or {}).values()]
            if e["eval"] != 1 and not e.get("failed"):
                n_d8 = solvers.count("Dopri8")
                classes.setdefault(str(n_d8), []).append(float(e["wall_s"]))
                if n_d8 == 0 and not event:
                    classes.setdefault("0, no event", []).append(float(e["wall_s"]))
            for scene, rec in (e.get("solver") or {}).items():
                if rec["config"]["solver"] != "Dopri8":
                    continue
                dopri8[scene] += 1
                w = why.setdefault(scene, {"after_drift": 0, "drifts": [],
                                           "after_half_step_check": 0, "other": 0})
                drifts = re.findall(rf"{re.escape(scene)}: the work-energy balance drifted by ([0-9.e+-]+)",
                                    event)
                if drifts:
                    w["after_drift"] += 1
                    w["drifts"].append(float(drifts[-1]))
                elif f"{scene}: the objective moved by" in event:
                    w["after_half_step_check"] += 1
                else:
                    w["other"] += 1
    n = len(evals) + len(first)
    t = np.asarray(evals)
    return {
        "runs": len(runs), "evaluations_per_run": per_run, "evaluations": n, "failed": failed,
        "failed_step_budget": budget, "failed_step_budget_share": budget / n if n else None,
        "failed_other": dict(reasons), "dopri8_evaluations_per_scene": dict(dopri8),
        "dopri8_why_per_scene": {scene: {**w, "drifts": sorted(w["drifts"])}
                                 for scene, w in why.items()},
        "eval_s_after_the_first": {
            "median": float(np.median(t)), "p90": float(np.percentile(t, 90)),
            "max": float(t.max()), "mean": float(t.mean()), "count": int(t.size)},
        "eval_s_by_dopri8_scenes": {
            k: {"count": len(v), "median": float(np.median(v)), "max": float(max(v))}
            for k, v in sorted(classes.items())},
        "first_eval_s": {"median": float(np.median(first)), "max": float(max(first))},
        "worker_s_total": float(t.sum() + sum(first)),
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--task", default="focus-vs-protect")
    p.add_argument("--weights", default="0,0.2,0.4,0.6,0.8,1")
    p.add_argument("--starts", default="20,30")
    p.add_argument("--max-evals", type=int, default=12)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--out", type=Path, default=Path("runs/bench-front-evaluations"))
    p.add_argument("--name", default="bench_front_evaluations",
                   help="the report's file name in --out and benchmarks/results/ (no .json)")
    p.add_argument("--report-only", action="store_true",
                   help="report the runs in --out, run nothing")
    args = p.parse_args(argv)
    weights = [float(w) for w in args.weights.split(",")]
    starts = [float(s) for s in args.starts.split(",")]

    args.out.mkdir(parents=True, exist_ok=True)
    load_start = os.getloadavg()[0]
    start = time.perf_counter()
    complete = True
    path = args.out / f"{args.name}.json"
    if args.report_only:  # complete when every run recorded its budget (below)
        # the wall time and load of the invocation that ran the sweep, if it wrote its report
        earlier = json.loads(path.read_text()) if path.exists() else {}
        wall, load = earlier.get("sweep_wall_s_this_invocation"), earlier.get("load_1min")
    else:
        from design_engine.sweeps.pareto_sweep import run_sweep

        try:
            run_sweep(args.task, args.out, weights=weights, starts=starts,
                      max_evals=args.max_evals, workers=args.workers, progress=True)
        except KeyboardInterrupt:
            complete = False
        wall = time.perf_counter() - start
        load = [load_start, os.getloadavg()[0]]
    summary = summarise(args.out)
    per_run = summary["evaluations_per_run"]
    complete = complete and len(per_run) == len(weights) * len(starts) and \
        min(per_run) >= args.max_evals
    report = {"task": args.task, "weights": args.weights, "starts": args.starts,
              "max_evals": args.max_evals, "workers": args.workers, "complete": complete,
              "sweep_wall_s_this_invocation": wall, "load_1min": load,
              "machine": {"platform": platform.platform(), "cpu": cpu_model(),
                          "cpus": os.cpu_count()},
              **summary}
    path.write_text(json.dumps(report, indent=2))
    shutil.copy(path, HERE / "results" / path.name)
    e = report["eval_s_after_the_first"]
    print(f"{report['evaluations']} evaluations in {report['runs']} runs: "
          f"{report['failed_step_budget']} used up the step budget "
          f"({100 * (report['failed_step_budget_share'] or 0):.1f} %), "
          f"{report['failed'] - report['failed_step_budget']} failed otherwise; an evaluation "
          f"after the first: median {e['median']:.1f} s, 90 % {e['p90']:.1f} s, longest "
          f"{e['max']:.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
