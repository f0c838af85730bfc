"""Parallel efficiency of `metarig pareto`: the same sweep on 1 and on N local workers.

Both sweeps run one after the other in this process, from empty folders, with the persistent
compilation cache warmed first (so neither pays compilation the other does not), and the ratio
of their wall times is reported with the machine's load. JSON in --out/bench_pareto.json.

It also splits the ratio: `eval_s_total` is the time the runs spent evaluating designs (the sum of
every evaluation's `wall_s` in the runs' histories). With N workers busy at once an evaluation may
take longer than alone (shared caches, memory bandwidth, clock): `contention` is the ratio of the
two totals, and `speedup x contention / N` is the efficiency of the sweep's own scheduling.

    .venv/bin/python benchmarks/bench_pareto.py --workers 2
"""

import argparse
import json
import os
import platform
import shutil
import time
from pathlib import Path


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--task", default="splitting")
    p.add_argument("--size", default="12x8")
    p.add_argument("--weights", default="0.25,0.5,0.75,1.0")
    p.add_argument("--starts", default="20,30")
    p.add_argument("--max-evals", type=int, default=10)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--out", type=Path, default=Path("runs/bench-pareto"))
    args = p.parse_args(argv)

    from design_engine.sweeps.pareto_sweep import run_sweep

    size = tuple(int(v) for v in args.size.split("x"))
    weights = [float(w) for w in args.weights.split(",")]
    starts = [float(s) for s in args.starts.split(",")]
    args.out.mkdir(parents=True, exist_ok=True)
    report = {"machine": {"platform": platform.platform(), "cpus": os.cpu_count()},
              "sweep": {"task": args.task, "size": args.size, "weights": weights,
                        "starts": starts, "max_evals": args.max_evals}, "runs": {}}
    warm = args.out / "warm"
    shutil.rmtree(warm, ignore_errors=True)
    run_sweep(args.task, warm, weights[:1], starts[:1], max_evals=2, size=size, workers=1,
              progress=False)
    for n in (1, args.workers):
        folder = args.out / f"workers{n}"
        shutil.rmtree(folder, ignore_errors=True)
        load0 = os.getloadavg()
        t0 = time.perf_counter()
        res = run_sweep(args.task, folder, weights, starts, max_evals=args.max_evals, size=size,
                        workers=n, progress=True)
        evals = [e for h in folder.glob("runs/*/history.json")
                 for e in json.loads(h.read_text())["evaluations"]]
        report["runs"][str(n)] = {"wall_s": time.perf_counter() - t0, "points": res["points"],
                                  "eval_s_total": sum(e["wall_s"] for e in evals),
                                  "load_average_before": load0,
                                  "load_average_after": os.getloadavg()}
        (args.out / "bench_pareto.json").write_text(json.dumps(report, indent=1))
    one, many = report["runs"]["1"]["wall_s"], report["runs"][str(args.workers)]["wall_s"]
    report["speedup"] = one / many
    report["contention"] = (report["runs"][str(args.workers)]["eval_s_total"]
                            / report["runs"]["1"]["eval_s_total"])
    report["scheduling_efficiency"] = report["speedup"] * report["contention"] / args.workers
    (args.out / "bench_pareto.json").write_text(json.dumps(report, indent=1))
    print(f"1 worker {one:.1f} s, {args.workers} workers {many:.1f} s: speedup {one / many:.2f}x; "
          f"an evaluation took {report['contention']:.2f}x as long with {args.workers} busy; "
          f"scheduling efficiency {report['scheduling_efficiency']:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
