"""One task's runs from several starts, side by side: does a configuration's result depend on
its start more than on the configuration?

Reads reports of `bench_design_contact.py` (one per start: the task's own, `--seed N`), each
with its run folders beside it (REPORT's folder/<label>/history.json), and writes, per start
and configuration: the best feasible objective after each evaluation (the run's own
objective), the evaluation that reached it, the wall time of the evaluations, the true
objective of its best design (the report's re-evaluation on the reference model) and that
design's largest constraint value under today's constraints (`max_constraint_now`: a run
recorded before a constraint was added may hold a design that breaks it); per configuration,
the median over the starts and how many reach `--target`.

    .venv/bin/python benchmarks/bench_design_starts.py [TAG=]REPORT.json [[TAG=]REPORT.json ...]
        [--target 0.01] [--name NAME] [--out DIR]

`TAG=` names the reports' configurations "<label> (TAG)", so that reports of two versions
(a configuration before and after a change) stay apart.

Writes OUT/NAME.json and .png (default benchmarks/results/bench_design_starts.*): the best
feasible objective against the evaluation (left) and against the wall time (right), one
colour per configuration, one line style per start.
"""

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from machine import write_report

HERE = Path(__file__).resolve().parent


class StartsError(ValueError):
    """A report or run folder that cannot be read (one line)."""


def best_feasible_curve(history: list[dict], goal: str) -> list[float | None]:
    """The best feasible objective after each evaluation (None before the first feasible)."""
    sign = 1.0 if goal == "max" else -1.0
    best, out = None, []
    for rec in history:
        f = rec.get("objective")
        if rec.get("feasible") and f is not None and np.isfinite(f):
            if best is None or sign * f > sign * best:
                best = f
        out.append(best)
    return out


def constraint_now(out: Path, report: dict, folder: Path, evaluation: int) -> float:
    """The largest constraint value of a run's design at `evaluation` (1-based) under the
    constraints of this checkout (rad or mm; feasible where <= 0)."""
    from design_engine.design.constraints import all_constraints
    from design_engine.design.task import load_task

    task = load_task(out / f"{report['task']}-static.toml")
    x = task.embed(np.load(folder / "checkpoint.npz")["x"][evaluation - 1])
    return float(np.max(np.asarray(all_constraints(task.lattice, x, task.limits))))


def read_start(path: Path, tag: str | None = None) -> dict:
    """One report: its start and, per configuration ("<label> (tag)" with a tag), its curve
    and figures."""
    try:
        report = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise StartsError(f"{path}: not a readable report ({exc})") from None
    seed, amplitude = report.get("seed"), report.get("random_amplitude")
    name = "the task's start" if seed is None else f"seed {seed}"
    if seed is not None and amplitude is not None:
        name = f"the task's start moved ({amplitude:g}, seed {seed})"
    start = {"report": str(path), "start": name, "seed": seed, "random_amplitude": amplitude,
             "task": report.get("task"), "runs": {}}
    for label, run in report.get("runs", {}).items():
        folder = path.parent / label
        try:
            record = json.loads((folder / "history.json").read_text())
        except (OSError, ValueError) as exc:
            raise StartsError(f"{folder}: no readable history.json ({exc})") from None
        history = record["evaluations"]
        curve = best_feasible_curve(history, record.get("goal", "max"))
        walls = np.cumsum([h["wall_s"] for h in history]).tolist()
        best = curve[-1]
        best_eval = None if best is None else curve.index(best) + 1
        start["runs"][label if tag is None else f"{label} ({tag})"] = {
            "evaluations": len(history), "wall_s": walls[-1] if walls else 0.0,
            "best_feasible": best,
            "best_eval": best_eval,
            "max_constraint_now": (None if best_eval is None
                                   else constraint_now(path.parent, report, folder, best_eval)),
            "true_objective": (run.get("true_ramp") or {}).get("objective"),
            "load_1min": run.get("load_1min"), "curve": curve, "wall_after": walls}
    return start


def merge_starts(starts: list[dict]) -> list[dict]:
    """Reports of the same start (the same seed) as one start, their configurations together
    (a configuration in two reports of one start: the later one's)."""
    merged: dict = {}
    for start in starts:
        key = (start["task"], start["seed"], start["random_amplitude"])
        if key in merged:
            merged[key]["runs"].update(start["runs"])
            merged[key]["report"] += f", {start['report']}"
        else:
            merged[key] = {**start, "runs": dict(start["runs"])}
    return list(merged.values())


def summarise(starts: list[dict], target: float | None) -> dict:
    """Per configuration over the starts: the best feasible objectives, their median, and how
    many reach `target` (own objective)."""
    labels = sorted({label for s in starts for label in s["runs"]})
    out = {}
    for label in labels:
        bests = [s["runs"][label]["best_feasible"] for s in starts if label in s["runs"]]
        bests = [b for b in bests if b is not None]
        out[label] = {"best_feasible": bests,
                      "median": float(np.median(bests)) if bests else None,
                      "reach_target": (None if target is None
                                       else sum(b >= target for b in bests)),
                      "starts": len(bests)}
    return out


def plot(starts: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (by_eval, by_time) = plt.subplots(1, 2, figsize=(11, 4.2), sharey=True)
    colours, styles = {}, ["-", "--", ":", "-."]
    for k, start in enumerate(starts):
        for label, run in start["runs"].items():
            colour = colours.setdefault(label, f"C{len(colours)}")
            pts = [(i + 1, t, v) for i, (t, v) in enumerate(zip(run["wall_after"], run["curve"]))
                   if v is not None]
            kw = dict(color=colour, ls=styles[k % len(styles)], lw=1.2,
                      label=f"{label}, {start['start']}")
            by_eval.plot([i for i, _, _ in pts], [v * 1e3 for *_, v in pts], **kw)
            by_time.plot([t for _, t, _ in pts], [v * 1e3 for *_, v in pts], **kw)
    by_eval.set_xlabel("evaluation")
    by_time.set_xlabel("wall time of the evaluations (s)")
    by_time.set_xscale("log")
    by_eval.set_ylabel("best feasible objective (mJ)")
    by_eval.legend(fontsize=7)
    for ax in (by_eval, by_time):
        ax.grid(alpha=0.3)
    task = starts[0].get("task") if starts else ""
    fig.suptitle(f"{task}: each configuration from {len(starts)} starts")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("reports", nargs="+", help="bench_design_contact.py reports, each as PATH "
                                              "or TAG=PATH")
    p.add_argument("--target", type=float, help="an objective to reach (the task's units, "
                                                 "SI: 0.01 for the focusing task's 10 mJ)")
    p.add_argument("--name", default="bench_design_starts")
    p.add_argument("--out", type=Path, default=HERE / "results")
    args = p.parse_args(argv)
    try:
        read = [read_start(Path(arg.split("=", 1)[1]), arg.split("=", 1)[0]) if "=" in arg
                else read_start(Path(arg)) for arg in args.reports]
    except StartsError as exc:
        print(f"bench_design_starts: error: {exc}", file=sys.stderr)
        return 2
    starts = merge_starts(read)
    tasks = {s["task"] for s in starts}
    if len(tasks) > 1:
        print(f"bench_design_starts: error: the reports are of different tasks {sorted(tasks)}",
              file=sys.stderr)
        return 2
    summary = summarise(starts, args.target)
    path = write_report(args.out, args.name, {"target": args.target, "summary": summary,
                                              "starts": starts})
    plot(starts, path.with_suffix(".png"))
    for start in starts:
        for label, run in start["runs"].items():
            best = run["best_feasible"]
            print(f"{start['start']:<18} {label:<10} {run['wall_s']:7.0f} s  best feasible "
                  + ("none" if best is None else
                     f"{best:.4e} (evaluation {run['best_eval']}; largest constraint today "
                     f"{run['max_constraint_now']:.3g})"))
    for label, s in summary.items():
        print(f"{label:<10} median {s['median']}" + (
            "" if args.target is None else f", {s['reach_target']} of {s['starts']} reach "
                                           f"{args.target:g}"))
    print(f"wrote {path} and {path.with_suffix('.png').name}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
