"""Where should the design loop's step check measure a design that starts in static contact?

The check re-measures the highest natural frequency of each new design before its fixed-step
solve (`design.evaluator`, power iteration on the Hessian). For a scene with a static
pre-compression it can measure at the design's own equilibrium (what the evaluator does now:
solved once before the solve, which then starts its static solve there) or, as it did before,
at the previous design's equilibrium under the new design's geometry. Along a run's designs
this script measures both (`policy.max_angular_frequency`, 300 cold iterations), and the
equilibrium's wall time.

    .venv/bin/python benchmarks/bench_step_check.py --run runs/fvp20 --evals 14 15 16 17 18 19 20 \
        --out benchmarks/results

Writes OUT/bench_step_check.json: per design, `own_hz`, `at_previous_hz` (the previous design
in the list; none for the first), their `ratio`, the smallest void's margin above the contact
asymptote at the own equilibrium (`void_margin_deg`) and `equilibrium_s`.
"""

import argparse
import json
import math
import time
from pathlib import Path

from machine import describe
from run_folder import run_designs


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--task", default="focus-vs-protect")
    p.add_argument("--scene", default="strain_8pct")
    p.add_argument("--run", type=Path, required=True, help="a `metarig design` run folder")
    p.add_argument("--evals", nargs="+", type=int, required=True)
    p.add_argument("--out", type=Path, default=Path("runs/bench-step-check"))
    args = p.parse_args(argv)
    task, xs = run_designs(p, args.task, args.run, args.scene)
    from design_engine.solve.policy import max_angular_frequency, static_void_margin
    from design_engine.solve.run import prestressed_state

    scene = task.scenes[args.scene]
    rows, previous = [], None
    for e in args.evals:
        if not 1 <= e <= len(xs):
            p.error(f"evaluation {e} is not in {args.run} (1-{len(xs)})")
        sc = scene.with_design(task.embed(xs[e - 1]))
        t0 = time.perf_counter()
        own_state = prestressed_state(sc)
        seconds = time.perf_counter() - t0
        own = max_angular_frequency(sc, state=own_state)
        at_prev = None if previous is None else max_angular_frequency(sc, state=previous)
        hz = 1e3 / (2 * math.pi)  # rad/ms -> Hz
        rows.append({"eval": e, "own_hz": own * hz,
                     "at_previous_hz": None if at_prev is None else at_prev * hz,
                     "ratio": None if at_prev is None else at_prev / own,
                     "void_margin_deg": math.degrees(static_void_margin(sc, own_state)),
                     "equilibrium_s": seconds})
        r = rows[-1]
        print(f"eval {e}: own {r['own_hz']:.0f} Hz, at the previous design's equilibrium "
              f"{r['at_previous_hz'] or float('nan'):.0f} Hz, equilibrium {seconds:.2f} s",
              flush=True)
        previous = own_state
    args.out.mkdir(parents=True, exist_ok=True)
    doc = {"task": args.task, "scene": args.scene, "run": str(args.run), "rows": rows,
           "machine": describe()}
    (args.out / "bench_step_check.json").write_text(json.dumps(doc, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
