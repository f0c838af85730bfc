"""When each part of a design run's evaluations runs, on which thread: the critical path.

Runs `metarig design TASK` (`--evals` evaluations, the task's own start) in this process as a
user gets it (the evaluator's threads, every core), from a compile cache of its own
(WORK/jax-cache, emptied first unless `--warm-cache`), and records for each call of the
evaluator's phases its thread, scene, start and end: the static equilibrium (`eq`), the
highest frequency (`freq`), each forward solve (`fwd`, with its configuration: order, step,
contact) and each reverse pass (`rev`). Per evaluation: its wall time and, per scene, the
seconds in each phase (a scene's phases run one after the other on its thread; the check's
solve started ahead runs beside them on another).

    .venv/bin/python benchmarks/bench_eval_timeline.py [--task focus-vs-protect] [--evals 20]
        [--warm-cache] [--name NAME] [--out DIR] [--work runs/bench-eval-timeline]

Writes OUT/NAME.json (default benchmarks/results/bench_eval_timeline.json); the run's folder is
WORK/NAME-run (removed first). Ctrl-C stops the run and writes what it has.
"""

import argparse
import functools
import os
import shutil
import sys
import threading
import time
from pathlib import Path

from machine import cpu_model, own_compile_cache, source_checkout, write_report

HERE = Path(__file__).resolve().parent
# the evaluator's methods timed, and their labels
PHASES = {"_equilibrium": "eq", "_frequency": "freq", "_solve": "fwd", "_gradient": "rev"}


def describe(config) -> str:
    """A forward solve's configuration in a few words."""
    solver = config.solver
    if not hasattr(solver, "max_dt"):
        return f"{type(solver).__name__}, contact"
    return (f"order {getattr(solver, 'order', 2)}, {solver.max_dt * 1e3:.1f} us"
            f"{', contact' if config.use_contact else ''}")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--task", default="focus-vs-protect")
    p.add_argument("--evals", type=int, default=20)
    p.add_argument("--warm-cache", action="store_true", help="keep WORK/jax-cache")
    p.add_argument("--name", default="bench_eval_timeline")
    p.add_argument("--out", type=Path, default=HERE / "results")
    p.add_argument("--work", type=Path, default=Path("runs/bench-eval-timeline"))
    args = p.parse_args(argv)
    if args.evals < 1:
        p.error("--evals must be at least 1")
    own_compile_cache(args.work, args.warm_cache)

    import design_engine  # noqa: F401  (x64, the cache)
    from design_engine.design import evaluator as evaluator_mod
    from design_engine.design.optimize import run_design
    from design_engine.design.task import TaskError, load_task

    origin = time.perf_counter()
    calls, evaluations = [], []
    last_scene: dict[str, str] = {}  # per thread, the scene of its last call (for `rev`)
    cls = evaluator_mod.TaskEvaluator

    def timed(method, label):
        @functools.wraps(method)
        def wrapper(self, *a, **k):
            start = time.perf_counter()
            try:
                return method(self, *a, **k)
            finally:
                thread = threading.current_thread().name
                if a and isinstance(a[0], str):
                    last_scene[thread] = a[0]
                scene = last_scene.get(thread, "")
                calls.append({"thread": thread, "phase": label,
                              "scene": scene,
                              "config": describe(a[1]) if label == "fwd" else "",
                              "start_s": start - origin,
                              "end_s": time.perf_counter() - origin})
        return wrapper

    for name, label in PHASES.items():
        setattr(cls, name, timed(getattr(cls, name), label))
    evaluate = cls.evaluate

    def measured(self, x):
        start = time.perf_counter()
        try:
            return evaluate(self, x)
        finally:
            evaluations.append({"eval": len(evaluations) + 1, "start_s": start - origin,
                                "end_s": time.perf_counter() - origin})
            print(f"evaluation {len(evaluations):3d}: "
                  f"{evaluations[-1]['end_s'] - evaluations[-1]['start_s']:6.2f} s", flush=True)

    cls.evaluate = measured
    try:
        task = load_task(args.task, max_evals=args.evals)
    except TaskError as exc:
        print(f"bench_eval_timeline: {exc}", file=sys.stderr)
        return 2
    folder = args.work / f"{args.name}-run"
    shutil.rmtree(folder, ignore_errors=True)
    load = [os.getloadavg()[0]]
    try:
        run_design(task, folder, resume=False, progress=False)
    except KeyboardInterrupt:
        print("interrupted: writing what was measured", file=sys.stderr)
    load.append(os.getloadavg()[0])
    for ev in evaluations:
        inside = [c for c in calls if ev["start_s"] <= c["start_s"] and c["end_s"] <= ev["end_s"]]
        ev["wall_s"] = ev["end_s"] - ev["start_s"]
        ev["calls"] = [dict(c, start_s=c["start_s"] - ev["start_s"],
                            end_s=c["end_s"] - ev["start_s"]) for c in inside]
        phases: dict = {}
        for c in inside:
            if c["phase"] == "fwd" and c["thread"].startswith("metarig-ahead"):
                key = "fwd_ahead"
            else:
                key = c["phase"]
            per = phases.setdefault(c["scene"] or "(scene)", {})
            per[key] = per.get(key, 0.0) + c["end_s"] - c["start_s"]
        ev["seconds"] = phases
    report = {"task": args.task, "evals": len(evaluations),
              "cache": "warm" if args.warm_cache else "empty",
              "machine": {"cpu": cpu_model(), "cores": os.cpu_count()}, "load_1min": load,
              "source": source_checkout(), "evaluations": evaluations}
    path = write_report(args.out, args.name, report)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
