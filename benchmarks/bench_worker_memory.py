"""A sweep worker's memory: a fresh process evaluates a design run's designs one after the other,
as a Dask worker does, with and without glibc's trim threshold (`MALLOC_TRIM_THRESHOLD_`,
`design_engine.sweeps.distributed.WORKER_ENV`); both processes run side by side and report
their resident memory after each evaluation. JSON in OUT/bench_worker_memory.json, copied to
benchmarks/results/.

    .venv/bin/python benchmarks/bench_worker_memory.py [--run runs/bench-design-contact-4/default]
        [--task focus-vs-protect] [--evals 9] [--out runs/bench-worker-memory]
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
TRIM = "MALLOC_TRIM_THRESHOLD_"


def _child(run: Path, task_name: str, evals: int) -> int:
    """Evaluate the run's first `evals` designs on one thread; one JSON line per evaluation."""
    import numpy as np

    import design_engine  # noqa: F401  (x64, cache)
    from design_engine.design.evaluator import EvaluationFailed, TaskEvaluator
    from design_engine.design.task import load_task

    task = load_task(task_name)
    xs = np.load(run / "checkpoint.npz")["x"]
    evaluator = TaskEvaluator(task, threads=1)
    page = os.sysconf("SC_PAGE_SIZE")
    for k in range(min(evals, len(xs))):
        try:
            evaluator.evaluate(task.embed(xs[k]))
            failed = False
        except EvaluationFailed:
            failed = True
        with open("/proc/self/statm") as f:
            rss = int(f.read().split()[1]) * page
        print(json.dumps({"eval": k + 1, "rss_gib": rss / 2**30, "failed": failed}), flush=True)
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--run", type=Path, default=Path("runs/bench-design-contact-4/default"))
    p.add_argument("--task", default="focus-vs-protect")
    p.add_argument("--evals", type=int, default=9)
    p.add_argument("--out", type=Path, default=Path("runs/bench-worker-memory"))
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.child:
        return _child(args.run, args.task, args.evals)
    if not (args.run / "checkpoint.npz").exists():
        raise SystemExit(f"{args.run} holds no design run (checkpoint.npz)")
    args.out.mkdir(parents=True, exist_ok=True)
    base = {k: v for k, v in os.environ.items() if k != TRIM}
    sides = {"trim 65536": dict(base, **{TRIM: "65536"}), "glibc default": base}
    procs = {}
    for label, env in sides.items():
        env = dict(env, METARIG_JAX_CACHE=str((args.out / f"jax-cache-{label[:4]}").resolve()))
        shutil.rmtree(env["METARIG_JAX_CACHE"], ignore_errors=True)
        procs[label] = subprocess.Popen(
            [sys.executable, __file__, "--child", "--run", str(args.run), "--task", args.task,
             "--evals", str(args.evals)], env=env, stdout=subprocess.PIPE, text=True)
    load = [os.getloadavg()[0]]
    rows = {}
    for label, proc in procs.items():
        out, _ = proc.communicate()
        if proc.returncode:
            raise SystemExit(f"the {label} process failed (exit {proc.returncode})")
        rows[label] = [json.loads(line) for line in out.splitlines() if line.startswith("{")]
        print(label, " ".join(f"{r['rss_gib']:.2f}" for r in rows[label]), "GiB")
    load.append(os.getloadavg()[0])
    report = {"run": str(args.run), "task": args.task, "evals": args.evals, "sides": rows,
              "load_1min": load, "machine": {"platform": platform.platform(),
                                             "cpu": cpu_model(), "cpus": os.cpu_count()}}
    path = args.out / "bench_worker_memory.json"
    path.write_text(json.dumps(report, indent=2))
    shutil.copy(path, HERE / "results" / path.name)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
