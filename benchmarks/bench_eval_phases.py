"""Where a design run's evaluations spend their time: compiling, tracing, solving, differentiating.

Runs one scalarised run of a Pareto sweep (`--task`, weight `--w1`, initial bias angle
`--start`, `--evals` evaluations) as a sweep's worker runs it: in this process, one solve at a
time, pinned to one core (`metarig.cores.pin_to_one_core`), from an empty compile cache of its
own (WORK/jax-cache; `--warm-cache` keeps the one a previous invocation left, so that XLA's
compilations come from it and tracing is what remains). Per evaluation: its wall time, the
seconds XLA spent compiling (and how many programs) and JAX spent tracing, and the seconds in
the evaluator's forward solves (half-step checks included), reverse passes, and step checks
(each design's static equilibrium and frequency). Totals after the first evaluation (which
compiles every scene's programs) give the share of compilation and tracing.

    .venv/bin/python benchmarks/bench_eval_phases.py [--task focus-vs-protect] [--w1 0.8]
        [--start 20] [--evals 12] [--core 0] [--warm-cache] [--name NAME] [--out DIR]
        [--work runs/bench-eval-phases]

Writes OUT/NAME.json (default benchmarks/results/bench_eval_phases.json); the design run's
folder is WORK/NAME-run (removed first). Ctrl-C stops the run and writes what it has.
"""

import argparse
import collections
import functools
import os
import shutil
import sys
import time
from pathlib import Path

from machine import cpu_model, own_compile_cache, source_checkout, write_report

HERE = Path(__file__).resolve().parent
PHASES = {"_solve": "solve_s", "_gradient": "gradient_s", "_check_step": "step_check_s"}
COMPILE = "/jax/core/compile/backend_compile_duration"
TRACE = "/jax/core/compile/jaxpr_trace_duration"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--task", default="focus-vs-protect")
    p.add_argument("--w1", type=float, default=0.8, help="weight of the task's first objective")
    p.add_argument("--start", type=float, default=20.0, help="initial bias angle, degrees")
    p.add_argument("--evals", type=int, default=12)
    p.add_argument("--core", type=int, default=0, help="the core to run on (modulo the cores "
                   "this process may use)")
    p.add_argument("--warm-cache", action="store_true", help="keep OUT/jax-cache")
    p.add_argument("--name", default="bench_eval_phases")
    p.add_argument("--out", type=Path, default=HERE / "results")
    p.add_argument("--work", type=Path, default=Path("runs/bench-eval-phases"),
                   help="the compile cache and the design run's folder")
    args = p.parse_args(argv)
    if args.evals < 2:
        p.error("--evals must be at least 2 (the first one compiles)")

    from metarig.cores import pin_to_one_core

    core = pin_to_one_core(args.core)  # before XLA starts
    own_compile_cache(args.work, args.warm_cache)

    import jax.monitoring

    import design_engine  # noqa: F401  (x64, the cache)
    from design_engine.design import evaluator as evaluator_mod
    from design_engine.design.optimize import run_design
    from design_engine.sweeps.pareto_sweep import RunSpec, _task

    spent = collections.Counter()

    def listen(event, seconds, **_):
        if event == COMPILE:
            spent["compile_s"] += seconds
            spent["programs"] += 1
        elif event == TRACE:
            spent["trace_s"] += seconds

    jax.monitoring.register_event_duration_secs_listener(listen)

    def timed(method, key):
        @functools.wraps(method)
        def wrapper(self, *a, **k):
            t = time.perf_counter()
            try:
                return method(self, *a, **k)
            finally:
                spent[key] += time.perf_counter() - t
        return wrapper

    cls = evaluator_mod.TaskEvaluator
    for name, key in PHASES.items():
        setattr(cls, name, timed(getattr(cls, name), key))
    rows = []
    evaluate = cls.evaluate

    def measured(self, x):
        before, t = spent.copy(), time.perf_counter()
        result = evaluate(self, x)
        row = {"eval": len(rows) + 1, "wall_s": time.perf_counter() - t}
        row.update({k: spent[k] - before[k] for k in
                    ("compile_s", "programs", "trace_s", *PHASES.values())})
        rows.append(row)
        print(f"evaluation {row['eval']:3d}: {row['wall_s']:6.2f} s, compiling "
              f"{row['compile_s']:5.2f} s ({row['programs']} programs), tracing "
              f"{row['trace_s']:5.2f} s", flush=True)
        return result

    cls.evaluate = measured
    try:
        task = _task(RunSpec(args.task, args.w1, args.start, args.evals, None))
    except Exception as exc:  # a bad task name or weight: one line
        print(f"bench_eval_phases: {exc}", file=sys.stderr)
        return 2
    folder = args.work / f"{args.name}-run"
    shutil.rmtree(folder, ignore_errors=True)
    load = [os.getloadavg()[0]]
    start = time.perf_counter()
    try:
        run_design(task, folder, resume=False, progress=False, threads=1)
    except KeyboardInterrupt:
        print("interrupted: writing what was measured", file=sys.stderr)
    wall = time.perf_counter() - start
    load.append(os.getloadavg()[0])
    later = rows[1:]
    total = {k: sum(r[k] for r in later) for k in ("wall_s", "compile_s", "trace_s",
                                                   *PHASES.values())}
    report = {
        "task": args.task, "w1": args.w1, "start_deg": args.start, "evals": len(rows),
        "cache": "warm" if args.warm_cache else "empty", "core": core,
        "machine": {"cpu": cpu_model(), "cores": os.cpu_count()}, "load_1min": load,
        "source": source_checkout(), "run_wall_s": wall, "evaluations": rows,
        "after_the_first": {**total, "programs": sum(r["programs"] for r in later),
                            "compile_and_trace_share": ((total["compile_s"] + total["trace_s"])
                                                        / total["wall_s"] if later else None)},
    }
    path = write_report(args.out, args.name, report)
    print(f"wrote {path}: after the first evaluation {total['wall_s']:.1f} s, of which "
          f"compiling {total['compile_s']:.1f} s and tracing {total['trace_s']:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
