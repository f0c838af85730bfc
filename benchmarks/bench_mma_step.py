"""The optimiser's own step, side by side: our sparse-dual MMA against NLopt's LD_MMA.

The same task and budget with each optimiser, one after the other in one process, so the
simulations (identical designs give identical solves) and the machine are shared. Reports per
evaluation the optimiser's own time (`opt_s`: between two objective evaluations, constraint
Jacobians excluded), the simulation time, and how far the designs of the two sequences are
apart (max |dx|, mm). JSON in --out/bench_mma_step.json.

    .venv/bin/python benchmarks/bench_mma_step.py --evals 6
"""

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--task", default="focusing")
    p.add_argument("--size", default=None, help="NXxNY (default the task's)")
    p.add_argument("--evals", type=int, default=6)
    p.add_argument("--algorithms", default="mma,nlopt-mma")
    p.add_argument("--out", type=Path, default=Path("runs/bench-mma-step"))
    args = p.parse_args(argv)

    import design_engine  # noqa: F401
    from design_engine.design.optimize import run_design
    from design_engine.design.task import load_task

    size = tuple(int(v) for v in args.size.split("x")) if args.size else None
    args.out.mkdir(parents=True, exist_ok=True)
    report = {"machine": {"platform": platform.platform(), "cpus": os.cpu_count(),
                          "load_average_start": os.getloadavg()},
              "task": args.task, "size": args.size, "runs": {}}
    xs = {}
    for algo in args.algorithms.split(","):
        task = load_task(args.task, size=size, max_evals=args.evals, algorithm=algo)
        folder = args.out / algo
        if (folder / "checkpoint.npz").exists():
            for f in folder.iterdir():
                f.unlink()
        t0 = time.perf_counter()
        res = run_design(task, folder, progress=True)
        xs[algo] = np.load(folder / "checkpoint.npz")["x"]
        ev = res.evaluations
        report["runs"][algo] = {
            "wall_s": time.perf_counter() - t0,
            "opt_s": [e["opt_s"] for e in ev], "sim_s": [e["sim_s"] for e in ev],
            "jac_s": [e["jac_s"] for e in ev], "objective": [e["objective"] for e in ev],
            "load_average_end": os.getloadavg(),
        }
        (args.out / "bench_mma_step.json").write_text(json.dumps(report, indent=1))
    algos = list(xs)
    if len(algos) >= 2:
        a, b = xs[algos[0]], xs[algos[1]]
        k = min(len(a), len(b))
        report["max_abs_dx_mm"] = [float(np.max(np.abs(a[i] - b[i]))) for i in range(k)]
    (args.out / "bench_mma_step.json").write_text(json.dumps(report, indent=1))
    for algo, r in report["runs"].items():
        later = r["opt_s"][1:]
        print(f"{algo:<12} optimiser step per evaluation: median {np.median(later):.3g} s, "
              f"max {np.max(later):.3g} s; simulation median {np.median(r['sim_s']):.3g} s")
    if "max_abs_dx_mm" in report:
        print("max |dx| between the sequences per evaluation (mm):",
              ", ".join(f"{v:.2g}" for v in report["max_abs_dx_mm"]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
