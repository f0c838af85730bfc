"""`metarig pareto`: the Pareto sweep of a two-objective task (weights x initial designs) on Dask."""

import argparse
import logging
import sys
from pathlib import Path

import numpy as np

from design_engine.sweeps.pareto_sweep import run_sweep
from metarig.argtypes import number_list, text

log = logging.getLogger("metarig.pareto")


def pareto_main(argv: list[str] | None = None) -> int:
    """Pareto sweep of a two-objective task: weights x initial designs, on Dask."""
    p = argparse.ArgumentParser(prog="metarig pareto", description=pareto_main.__doc__)
    p.add_argument("task", help="two-objective task preset (splitting, reprogram-location, "
                   "focus-vs-protect) or task file")
    p.add_argument("--out", type=Path, required=True, help="sweep folder")
    p.add_argument("--size", help="lattice size NXxNY (default the task's)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--weights", type=int, default=11, help="K weights w1 evenly in [0, 1] (default 11)")
    g.add_argument("--weight-list", type=number_list("weights"), help="explicit weights w1, comma-separated")
    p.add_argument("--starts", type=number_list("starts"), default=[15.0, 20.0, 25.0, 30.0, 35.0],
                   help="bias angles (deg) of the initial designs (default 15,20,25,30,35)")
    p.add_argument("--max-evals", type=int, help="evaluations per run (default the task's)")
    h = p.add_mutually_exclusive_group()
    h.add_argument("--workers", type=int, help="worker processes of a local cluster "
                   "(default one per core this process may use)")
    h.add_argument("--scheduler", type=text("--scheduler"),
                   help="address of an existing Dask scheduler (tcp://HOST:PORT)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    logging.getLogger("metarig").setLevel(logging.INFO)

    from metarig.argtypes import grid_size
    from design_engine.design.optimize import ResumeError
    from design_engine.design.task import TaskError

    try:
        size = None if args.size is None else grid_size(args.size)
        weights = (list(np.linspace(0.0, 1.0, args.weights)) if args.weight_list is None
                   else args.weight_list)
        if args.weight_list is None and args.weights < 1:
            raise ValueError("--weights must be at least 1")
        if not args.starts:
            raise ValueError("--starts needs at least one bias angle")
        if args.max_evals is not None and args.max_evals < 1:
            raise ValueError("--max-evals must be positive")
        if args.workers is not None and args.workers < 1:
            raise ValueError("--workers must be positive")
        result = run_sweep(args.task, args.out, [round(float(w), 6) for w in weights],
                           args.starts, max_evals=args.max_evals, size=size,
                           workers=args.workers, scheduler=args.scheduler,
                           progress=not args.quiet)
    except (TaskError, ResumeError, ValueError, OSError, argparse.ArgumentTypeError) as exc:
        print(f"metarig pareto: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"metarig pareto: stopped; points.json and front.json in {args.out} hold every "
              "evaluation so far; re-run the same command to continue", file=sys.stderr)
        return 130
    log.info("%d runs, %d evaluated designs, %d on the front, %.0f s: wrote %s",
             len(result["runs"]), result["points"], result["front"], result["wall_s"],
             ", ".join(str(args.out / n) for n in ("points.json", "front.json", "pareto.png")))
    if result["failed"]:
        print(f"metarig pareto: {len(result['failed'])} run(s) failed: " + "; ".join(
            f"{r['run']} ({r['failed']})" for r in result["failed"]), file=sys.stderr)
        return 1
    return 0
