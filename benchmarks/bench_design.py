"""Benchmark of the design loop: every task preset from its initial design at its spec budget.

For each preset: initial and best feasible objective, their ratio, evaluations, wall time, and
where an evaluation's time goes (simulation, constraint Jacobians, the optimiser's own step).
Each run keeps its run folder under --out/<preset>, so an interrupted benchmark resumes
(`--resume`) without repeating an evaluation. The JSON is rewritten after every preset.

    .venv/bin/python benchmarks/bench_design.py --out runs/bench-design
    .venv/bin/python benchmarks/bench_design.py --presets focusing --max-evals 60
    .venv/bin/python benchmarks/bench_design.py --presets focus-vs-protect --max-evals 3
"""

import argparse
import json
import os
import platform
import time
from pathlib import Path


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=Path("runs/bench-design"))
    p.add_argument("--presets", help="comma-separated presets (default: all)")
    p.add_argument("--max-evals", type=int, help="evaluation budget (default: each preset's)")
    p.add_argument("--algorithm", default=None, help="mma, nlopt-mma or nlopt-ccsaq")
    p.add_argument("--resume", action="store_true", help="continue runs found in --out")
    p.add_argument("--quiet", action="store_true")
    args = p.parse_args(argv)

    import jax

    import design_engine  # noqa: F401
    from design_engine.design.optimize import run_design
    from design_engine.design.run_outputs import write_outputs
    from design_engine.design.task import load_task, preset_names

    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "bench_design.json"
    report = json.loads(path.read_text()) if path.exists() else {"runs": {}}
    report["machine"] = {"platform": platform.platform(), "cpus": os.cpu_count(),
                         "jax": jax.__version__, "load_average_start": os.getloadavg()}
    for name in (args.presets.split(",") if args.presets else preset_names()):
        task = load_task(name, max_evals=args.max_evals, algorithm=args.algorithm)
        folder = args.out / name
        load0 = os.getloadavg()
        t0 = time.perf_counter()
        res = run_design(task, folder, resume=args.resume and (folder / "run.json").exists(),
                         progress=not args.quiet)
        wall = time.perf_counter() - t0
        write_outputs(task, folder, res, plots=True)
        ev = res.evaluations
        best = ev[res.best] if res.best is not None else None
        live = [e for e in ev if e["sim_s"] > 0]
        report["runs"][name] = {
            "evaluations": len(ev), "status": res.status, "stop_reason": res.stop_reason,
            "initial_objective": ev[0]["objective"],
            "best_objective": best and best["objective"], "best_eval": best and best["eval"],
            "ratio": (best["objective"] / ev[0]["objective"]) if best and ev[0]["objective"]
            else None,
            "wall_s": wall, "wall_s_recorded": sum(e["wall_s"] for e in ev),
            "per_eval_s": {k: sum(e[k] for e in live) / max(len(live), 1)
                           for k in ("wall_s", "sim_s", "jac_s", "opt_s")},
            "failed": sum(bool(e["failed"]) for e in ev),
            "contact_evals": sum(1 for e in ev if e["solver"] and any(
                s["config"]["use_contact"] for s in e["solver"].values())),
            "compilations": res.compilations,
            "load_average_start": load0, "load_average_end": os.getloadavg(),
        }
        path.write_text(json.dumps(report, indent=1))
    print(f"{'preset':<20}{'initial':>12}{'best':>12}{'ratio':>9}{'evals':>7}{'wall s':>9}"
          f"{'s/eval':>8}")
    for name, r in report["runs"].items():
        ratio = f"{r['ratio']:.1f}" if r["ratio"] else "-"
        print(f"{name:<20}{r['initial_objective']:>12.4g}{(r['best_objective'] or 0):>12.4g}"
              f"{ratio:>9}{r['evaluations']:>7}{r['wall_s']:>9.0f}"
              f"{r['per_eval_s']['wall_s']:>8.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
