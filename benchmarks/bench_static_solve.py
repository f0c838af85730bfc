"""Warm static equilibria of the focus-vs-protect task's scenes (24x18 at 1 % and 8 %), as the
design loop solves one per new design: this checkout against an earlier one, side by side.
Writes benchmarks/results/bench_static_solve.json.

    git worktree add /tmp/before REF
    .venv/bin/python benchmarks/bench_static_solve.py --before /tmp/before [--designs 3]
                                                      [--repeats 3] [--out FILE]

Each side runs in a fresh process (compilation cache off), one after the other: per scene, the
task's start design and `--designs - 1` seeded perturbations of it (0.03 mm per coordinate),
each solved once to compile and then `--repeats` times with the kept equilibria forgotten
(`statics.forget_equilibria`): the best wall time. The equilibria of the two sides are compared
to the bit (`same_bits`, `max_difference`); the exit code is 1 when any differs.
"""

import argparse
import json
import os
import sys
import tempfile
from pathlib import Path

import numpy as np

from bench_compile import child_json
from machine import describe

ROOT = Path(__file__).resolve().parent.parent
CHILD = """
import json, time
import numpy as np
from design_engine.design.task import load_task
from design_engine.physics import statics
from design_engine.solve.run import prestressed_state
designs, repeats, out = %(designs)d, %(repeats)d, %(out)r
task = load_task("focus-vs-protect")
rng = np.random.default_rng(0)
x0 = np.asarray(task.initial_design)
xs = [x0] + [x0 + 0.03 * rng.normal(size=x0.size) for _ in range(designs - 1)]
rows, states = [], {}
for name, scene in task.scenes.items():
    for k, x in enumerate(xs):
        s = scene.with_design(x)
        t = time.perf_counter(); prestressed_state(s); first = time.perf_counter() - t
        best = np.inf
        for _ in range(repeats):
            statics.forget_equilibria()
            t = time.perf_counter(); q = prestressed_state(s); best = min(best, time.perf_counter() - t)
        states[f"{name}/{k}"] = q
        rows.append({"scene": name, "design": k, "first_s": first, "warm_s": best})
np.savez(out, **states)
print(json.dumps(rows))
"""


def side(src: Path, designs: int, repeats: int, states: Path) -> list[dict]:
    """One side's rows, its equilibria saved to `states`."""
    return child_json(CHILD % {"designs": designs, "repeats": repeats, "out": str(states)}, src)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--before", type=Path, required=True, help="a checkout of an earlier commit")
    p.add_argument("--designs", type=int, default=3)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--out", type=Path, default=ROOT / "benchmarks/results/bench_static_solve.json")
    args = p.parse_args(argv)
    if args.designs < 1 or args.repeats < 1:
        p.error("--designs and --repeats must be at least 1")
    if not (args.before / "design_engine").is_dir():
        p.error(f"--before {args.before}: not a checkout of this project")
    load = [os.getloadavg()[0]]
    with tempfile.TemporaryDirectory() as tmp:
        paths = {k: Path(tmp) / f"{k}.npz" for k in ("before", "after")}
        print("before ...", flush=True)
        before = side(args.before, args.designs, args.repeats, paths["before"])
        print("after ...", flush=True)
        after = side(ROOT, args.designs, args.repeats, paths["after"])
        qb, qa = np.load(paths["before"]), np.load(paths["after"])
        rows = []
        for b, a in zip(before, after):
            key = f"{a['scene']}/{a['design']}"
            rows.append({"scene": a["scene"], "design": a["design"],
                         "warm_s": {"before": round(b["warm_s"], 4), "after": round(a["warm_s"], 4)},
                         "first_s": {"before": round(b["first_s"], 3), "after": round(a["first_s"], 3)},
                         "speedup": round(b["warm_s"] / a["warm_s"], 3),
                         "same_bits": bool(np.array_equal(qb[key], qa[key])),
                         "max_difference": float(np.max(np.abs(qb[key] - qa[key])))})
            print(json.dumps(rows[-1]), flush=True)
    load.append(os.getloadavg()[0])
    result = {"machine": describe(), "before": str(args.before),
              "load_average_1min": {"before": load[0], "after": load[1]},
              "designs": args.designs, "repeats": args.repeats, "rows": rows}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    same = sum(r["same_bits"] for r in rows)
    print(f"-> {args.out}: {same} of {len(rows)} equilibria the same to the bit")
    return 0 if same == len(rows) else 1  # a change of the equilibria fails the comparison


if __name__ == "__main__":
    sys.exit(main())
