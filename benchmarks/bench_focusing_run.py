"""The 60-evaluation focusing run (24x16) before and after a policy change, side by side, with an
accuracy re-check of the accepted solves (`--task` another task, e.g. focus-vs-protect).

Runs `metarig design focusing --max-evals N` twice in one benchmark, one after the other on the
same machine (or both at once with `--parallel`, so that each sees the same load): "before"
from a checkout of `--before REF` (a git worktree under OUT; default f3dda59, the policy that
handed a fixed step outgrown by the contact barrier to Dopri8 and kept Dopri8 while the designs
stayed in contact) and "after" from this checkout (or from a worktree of `--after REF`). Then a
sample of the "after" run's evaluations is re-checked: each design re-evaluated with the configuration that
counted for it and with Dopri8 at rtol 1e-10 / atol 1e-8 (contact, float64): relative error of
J and cosine of the gradients.

Each run compiles into a cache of its own (OUT/jax-cache-before, -after), empty when the run
starts afresh, as on a fresh machine. `--seed N` starts both runs from the seeded random design
of `metarig design --seed N` instead of the task's start (one start says little about the
quality of a policy: on this task the optimiser amplifies a 1e-5 difference of J about tenfold
an evaluation). Run folders OUT/before and OUT/after resume (`metarig design --resume`; a
resumed run's wall time is the sum of its evaluations' `wall_s`, stated as such);
OUT/bench_focusing_run.json is written after every part and OUT/bench_focusing_run.png (best
feasible J against wall time, and where each evaluation's time went) at the end.

`--replay FIRST LAST` instead replays evaluations FIRST..LAST of the stored "after" run (its
designs, `checkpoint.npz`) through a fresh task evaluator, once from a checkout of `--before`
and once from this one (or from `--after`), side by side (both at once when `--parallel`), each
from an empty compile cache of its own (OUT/jax-cache-replay-before, -after): per evaluation
its wall time, the objective and how many programs the evaluator had compiled
(OUT/bench_focusing_replay.json).

    .venv/bin/python benchmarks/bench_focusing_run.py --out runs/bench-focusing-run
    .venv/bin/python benchmarks/bench_focusing_run.py --evals 20 --recheck 3 --out /tmp/bfr
    .venv/bin/python benchmarks/bench_focusing_run.py --out runs/bench-focusing-run-mts \
        --before 9ea842d --after 17f6acc --parallel
    .venv/bin/python benchmarks/bench_focusing_run.py --out runs/bench-focusing-run \
        --replay 6 12 --before 35c7535
"""

import argparse
import json
import os
import shutil
import subprocess
import sys
import threading
import time
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from machine import describe

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
TASK = "focusing"
BEFORE_REF = "f3dda59"
RECHECK_RTOL, RECHECK_ATOL = 1e-10, 1e-8


def source_tree(out: Path, ref: str) -> Path:
    """A worktree of `ref` under `out` (created once)."""
    tree = out / f"src-{ref}"
    if not (tree / "design_engine").is_dir():
        subprocess.run(["git", "-C", str(REPO), "worktree", "add", "--detach", "--force",
                        str(tree), ref], check=True, capture_output=True)
    return tree


def run_design(src: Path, folder: Path, evals: int, seed: int | None = None,
               task: str = TASK) -> dict:
    """`metarig design TASK` from the sources in `src` into `folder` (resumed if it exists),
    from the task's start or, with `seed`, a seeded random one (`metarig design --seed`)."""
    history = folder / "history.json"
    done = _evaluations(history)
    if len(done) >= evals:
        return {"resumed": True, "ran_s": 0.0}
    cmd = [sys.executable, "-c", "import sys; from metarig.cli import main; sys.exit(main())",
           "design", task, "--max-evals", str(evals), "--out", str(folder), "--no-plots"]
    if history.exists():
        cmd.append("--resume")
    elif seed is not None:
        cmd += ["--seed", str(seed)]
    # a compilation cache of the run's own (empty at its start, as on a fresh machine), so
    # that programs another run compiled do not count for it
    cache = folder.parent / f"jax-cache-{folder.name}"
    if not done:
        shutil.rmtree(cache, ignore_errors=True)
    env = dict(os.environ, PYTHONPATH=str(src), METARIG_JAX_CACHE=str(cache))
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=src, env=env)
    if proc.returncode != 0:
        raise SystemExit(f"metarig design failed in {src} (exit {proc.returncode})")
    return {"resumed": bool(done), "ran_s": time.perf_counter() - t0}


def _evaluations(history: Path) -> list[dict]:
    return json.loads(history.read_text())["evaluations"] if history.exists() else []


def _kind(config: dict) -> str:
    name = config["solver"]
    if name == "FixedStepVerlet":
        name = "Verlet" + (" refined" if config.get("refined") else "")
        name += f" order {config['order']}" if config.get("order", 2) != 2 else ""
        name += " contact" if config["use_contact"] else " no contact"
        if config.get("contact_substeps", 1) > 1:
            name += f" x{config['contact_substeps']} substeps"
    return name


def _kinds(evaluation: dict) -> str:
    """What counted for an evaluation: each scene's configuration (`_kind`), joined by " + "."""
    return " + ".join(_kind(s["config"]) for s in evaluation["solver"].values())


def summarise(folder: Path, ran: dict) -> dict:
    """Best feasible objective, wall time and which configuration counted, from the history."""
    evals = _evaluations(folder / "history.json")
    feasible = [e["objective"] for e in evals if e["feasible"] and not e["failed"]]
    walls = np.array([e["wall_s"] for e in evals])
    kinds = [_kinds(e) for e in evals if not e["failed"]]
    events = " ".join(e["event"] or "" for e in evals)
    return {
        "evaluations": len(evals), "failed": sum(e["failed"] for e in evals),
        "best_feasible_J": max(feasible) if feasible else None,
        "wall_s": ran["ran_s"] if not ran["resumed"] else None,
        "sum_eval_wall_s": float(walls.sum()), "median_eval_s": float(np.median(walls)),
        "max_eval_s": float(walls.max()), "counted": dict(Counter(kinds)),
        "seconds_by_kind": {k: float(sum(e["wall_s"] for e in evals if not e["failed"]
                                         and _kinds(e) == k))
                            for k in set(kinds)},
        "refined": events.count("re-solved once at"),
        "substepped": events.count("contact forces stepped"),
        "to_dopri8": events.count("Dopri8"),
        "curve": [[float(walls[: i + 1].sum()), e["objective"], bool(e["feasible"])]
                  for i, e in enumerate(evals)],
        "kinds": [_kinds(e) if not e["failed"] else "failed" for e in evals],
        "walls": walls.tolist(),
    }


def _config(summary: dict):
    import diffrax

    from design_engine.solve.fixed_step import FixedStepVerlet
    from design_engine.solve.simulate import SolverConfig

    if summary["solver"] == "FixedStepVerlet":
        solver = FixedStepVerlet(max_dt=summary["max_dt_s"] * 1e3,
                                 refined=bool(summary.get("refined", False)),
                                 remat=bool(summary.get("remat", False)),
                                 contact_substeps=int(summary.get("contact_substeps", 1)),
                                 order=int(summary.get("order", 2)))
        return SolverConfig(solver=solver, use_contact=summary["use_contact"],
                            dtype=summary["dtype"])
    return SolverConfig(solver=getattr(diffrax, summary["solver"])(), rtol=summary["rtol"],
                        atol=summary["atol"], use_contact=summary["use_contact"],
                        dtype=summary["dtype"])


def recheck(folder: Path, evals: int, count: int, rows: list[dict], save,
            task_name: str = TASK) -> list[dict]:
    """Re-evaluate `count` evaluations of the run in `folder`, evenly spread, scene by scene
    with the configuration that counted for the scene and with tight Dopri8; rows already in
    `rows` are kept."""
    import dataclasses

    import diffrax

    from design_engine.design.evaluator import TaskEvaluator
    from design_engine.design.task import load_task
    from design_engine.solve.simulate import SolverConfig

    history = _evaluations(folder / "history.json")
    xs = np.load(folder / "checkpoint.npz")["x"]
    ok = [e for e in history if not e["failed"]]
    picks = [ok[int(round(i))] for i in np.linspace(0, len(ok) - 1, count)] if ok else []
    task = load_task(task_name, max_evals=evals)
    tight = SolverConfig(solver=diffrax.Dopri8(), rtol=RECHECK_RTOL, atol=RECHECK_ATOL,
                         max_steps=400_000)
    seen = {(r["eval"], r.get("scene", "pulse")) for r in rows}
    for e in picks:
        for scene, counted in e["solver"].items():
            if (e["eval"], scene) in seen:
                continue
            x = task.embed(xs[e["eval"] - 1])
            alone = dataclasses.replace(task, terms=tuple(t for t in task.terms
                                                          if t.scene == scene))
            t0 = time.perf_counter()
            used = TaskEvaluator(alone, _config(counted["config"])).evaluate(x)
            t1 = time.perf_counter()
            ref = TaskEvaluator(alone, tight).evaluate(x)
            t2 = time.perf_counter()
            cos = float(np.dot(used.grad, ref.grad)
                        / (np.linalg.norm(used.grad) * np.linalg.norm(ref.grad)))
            rows.append({"eval": e["eval"], "scene": scene, "config": _kind(counted["config"]),
                         "J": used.value, "J_reference": ref.value,
                         "J_rel_err": abs(used.value - ref.value) / abs(ref.value),
                         "grad_cosine": cos, "config_s": t1 - t0, "reference_s": t2 - t1})
            print(f"  evaluation {e['eval']}, {scene} ({rows[-1]['config']}): J error "
                  f"{rows[-1]['J_rel_err']:.2e}, gradient cosine {cos:.6f}", flush=True)
            save()
    return rows


def plot(report: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4.2))
    colors = {"Dopri8": "C3", "failed": "k"}
    for k, (label, res) in enumerate(report["runs"].items()):
        curve = np.array([[c[0], c[1] if c[2] and c[1] is not None else np.nan]
                          for c in res["curve"]])  # a failed evaluation has no objective
        best = np.fmax.accumulate(np.nan_to_num(curve[:, 1], nan=-np.inf))
        a.plot(curve[:, 0] / 60, best * 1e3, "-", color=f"C{k}",
               label=f"{label}: {res['sum_eval_wall_s'] / 60:.1f} min")
        x0 = np.arange(len(res["walls"])) + (0.4 * k - 0.2)
        for kind in sorted(set(res["kinds"])):
            sel = [i for i, kk in enumerate(res["kinds"]) if kk == kind]
            b.bar(x0[sel], np.array(res["walls"])[sel], width=0.4,
                  color=colors.get(kind, f"C{4 + sorted(set(res['kinds'])).index(kind)}"),
                  edgecolor=f"C{k}", linewidth=0.8, label=f"{label}: {kind}")
    a.set_xlabel("wall time, min (sum of evaluations)")
    a.set_ylabel("best feasible J / N_t, mJ")
    a.legend(fontsize=8)
    a.set_title(f"{report.get('task', TASK)}, {report['evals']} evaluations", fontsize=9)
    b.set_xlabel("evaluation")
    b.set_ylabel("wall time, s")
    b.legend(fontsize=6)
    b.set_title("what each evaluation cost and which solve counted", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# a task evaluator over stored designs: argv = checkpoint.npz, first, last, output JSON, task
REPLAY = """
import json, sys, time
import numpy as np
from design_engine.design.evaluator import TaskEvaluator
from design_engine.design.task import load_task
xs = np.load(sys.argv[1])["x"]
first, last = int(sys.argv[2]), int(sys.argv[3])
task = load_task(sys.argv[5])
t0 = time.perf_counter()
ev = TaskEvaluator(task)
rows = [{"eval": 0, "wall_s": time.perf_counter() - t0, "compilations": ev.compilations}]
for i in range(first, last + 1):
    t0 = time.perf_counter()
    out = ev.evaluate(task.embed(xs[i - 1]))
    rows.append({"eval": i, "wall_s": time.perf_counter() - t0, "value": out.value,
                 "compilations": ev.compilations,
                 "config": {k: v["config"] for k, v in out.solver.items()},
                 "events": list(out.events)})
    print(json.dumps(rows[-1]), flush=True)
json.dump(rows, open(sys.argv[4], "w"))
"""


def replay(out: Path, before: str, first: int, last: int, parallel: bool,
           after: str | None = None, task: str = TASK) -> dict:
    """Evaluations `first`..`last` of the stored "after" run through a fresh evaluator, from
    the sources of `before` and of `after` (default: this checkout; see module docstring)."""
    checkpoint = out / "after" / "checkpoint.npz"
    procs, files = {}, {}
    after_src = REPO if after is None else source_tree(out, after)
    for label, src in (("before", source_tree(out, before)), ("after", after_src)):
        files[label] = out / f"replay_{label}.json"
        cmd = [sys.executable, "-c", REPLAY, str(checkpoint), str(first), str(last),
               str(files[label]), task]
        cache = out / f"jax-cache-replay-{label}"  # empty: each side compiles its own
        shutil.rmtree(cache, ignore_errors=True)
        env = dict(os.environ, PYTHONPATH=str(src), METARIG_JAX_CACHE=str(cache))
        t0, load0 = time.perf_counter(), os.getloadavg()[0]
        procs[label] = (subprocess.Popen(cmd, cwd=src, env=env), t0, load0)
        if not parallel:
            procs[label][0].wait()
    result = {"first": first, "last": last, "before_ref": before, "after_ref": after,
              "parallel": parallel, "sides": {}}
    for label, (proc, t0, load0) in procs.items():
        if proc.wait() != 0:
            raise SystemExit(f"replay {label} failed (exit {proc.returncode})")
        rows = json.loads(files[label].read_text())
        result["sides"][label] = {"rows": rows, "compilations": rows[-1]["compilations"],
                                  "wall_s": sum(r["wall_s"] for r in rows),
                                  "process_wall_s": time.perf_counter() - t0,
                                  "load_start": load0, "load_end": os.getloadavg()[0]}
    return result


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=Path("runs/bench-focusing-run"))
    p.add_argument("--task", default=TASK, help="the task (preset or file) both runs design")
    p.add_argument("--evals", type=int, default=60)
    p.add_argument("--before", default=BEFORE_REF, help="git ref of the 'before' policy")
    p.add_argument("--after", help="git ref of the 'after' policy (default: this checkout)")
    p.add_argument("--seed", type=int, help="both runs start from the seeded random design "
                   "(`metarig design --seed`) instead of the task's start")
    p.add_argument("--recheck", type=int, default=6, help="evaluations of the 'after' run "
                   "re-checked against tight Dopri8 (0: none)")
    p.add_argument("--only", choices=("before", "after"), help="run one side only")
    p.add_argument("--replay", nargs=2, type=int, metavar=("FIRST", "LAST"),
                   help="replay these evaluations of the stored 'after' run, before and after")
    p.add_argument("--parallel", action="store_true",
                   help="both sides at once (the runs, or with --replay the replays)")
    args = p.parse_args(argv)
    out = args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    if args.replay:
        res = replay(out, args.before, *args.replay, args.parallel, args.after, args.task) | {
            "machine": describe()}
        (out / "bench_focusing_replay.json").write_text(json.dumps(res, indent=1))
        for label, side in res["sides"].items():
            print(f"{label}: {side['wall_s']:.0f} s, {side['compilations']} programs")
        return 0
    path = out / "bench_focusing_run.json"
    report = json.loads(path.read_text()) if path.exists() else {}
    report.update(task=args.task, evals=args.evals, before_ref=args.before, machine=describe(),
                  seed=args.seed)
    report.setdefault("runs", {})

    lock = threading.Lock()  # the two sides of --parallel save from their own threads

    def save():
        with lock:
            tmp = path.with_suffix(".json.tmp")
            tmp.write_text(json.dumps(report, indent=1))
            tmp.replace(path)

    sides = {"before": lambda: source_tree(out, args.before),
             "after": lambda: source_tree(out, args.after) if args.after else REPO}
    sides = {k: v for k, v in sides.items() if not args.only or k == args.only}

    def run_side(label):
        print(f"{label}: metarig design {args.task} --max-evals {args.evals}", flush=True)
        load0 = os.getloadavg()[0]
        ran = run_design(sides[label](), out / label, args.evals, args.seed, args.task)
        res = summarise(out / label, ran)
        if ran["resumed"] and label in report["runs"]:
            res["wall_s"] = report["runs"][label].get("wall_s")
        report["runs"][label] = res | {"load_start": load0, "load_end": os.getloadavg()[0],
                                       "parallel": args.parallel}
        save()

    if args.parallel:  # both sides at once: the same load on each
        with ThreadPoolExecutor(len(sides)) as pool:
            list(pool.map(run_side, sides))
    else:
        for label in sides:
            run_side(label)
    if args.recheck and (out / "after" / "history.json").exists():
        print(f"re-check: {args.recheck} evaluations of 'after' against Dopri8 rtol "
              f"{RECHECK_RTOL:g}", flush=True)
        report["recheck"] = recheck(out / "after", args.evals, args.recheck,
                                    report.get("recheck", []), save, args.task)
        save()
    plot(report, out / "bench_focusing_run.png")
    for label, res in report["runs"].items():
        print(f"{label}: best feasible {res['best_feasible_J']}, {res['sum_eval_wall_s']:.0f} s "
              f"over {res['evaluations']} evaluations, counted {res['counted']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
