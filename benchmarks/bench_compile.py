"""Compile time of a precompressed scene's forward pass (value and pullback, the design loop's
and `make_objective`'s first program) with its static equilibrium solved inside the program
against handed to it (`simulate(..., equilibrium=)`, as `run.static_equilibrium` does), and of
the static solver itself (compiled once per topology). Writes
benchmarks/results/bench_compile.json.

    .venv/bin/python benchmarks/bench_compile.py [--scenes [small] [full]] [--before DIR]
                                                 [--repeats N] [--out FILE]

`--before DIR` (a checkout of an earlier commit, e.g. `git worktree add DIR REF`) also times the
default experiment (24x16 at 2 %, static start) as a new user first runs it: `simulate_scene`
in a fresh process with the cache off, the first call (compilation included) and a second one,
from DIR and from this checkout (`--repeats N`: N times, alternating).

Each scene runs in a fresh process with the compilation cache off. Per program: XLA's lowering
and compilation (`jit(...).lower(...)` and `.compile()`, s) and one run of the compiled program;
the two forward passes' values must agree (relative difference recorded). The policy's own
configuration for the scene (`choose_config`) is compiled; the load average is recorded before
and after.
"""

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

from machine import describe

ROOT = Path(__file__).resolve().parent.parent
SCENES = {
    "small": ("protection-24x18 6x6 at 7 %, 2 mm pulse (the tests' jammed scene)",
              'build_scene("protection-24x18", nx=6, ny=6, strain=0.07, amplitude_m=2e-3)'),
    "full": ("protection-24x18 at 8 % (focus-vs-protect's protection scene)",
             'build_scene("protection-24x18", strain=0.08)'),
}

CHILD = """
import json, time
import jax, jax.numpy as jnp, numpy as np
import design_engine
from design_engine.physics.scenes import build_scene
from design_engine.physics.statics import make_static_solver
from design_engine.solve.policy import choose_config
from design_engine.solve.run import _split_objective, config_summary, static_equilibrium

scene = %s
config = choose_config(scene).config
x = jnp.asarray(scene.design)
out = {"config": config_summary(config)}

def timed(name, jitted, *args):
    t = time.perf_counter(); lowered = jitted.lower(*args); t1 = time.perf_counter()
    compiled = lowered.compile(); t2 = time.perf_counter()
    result = jax.block_until_ready(compiled(*args)); t3 = time.perf_counter()
    out[name] = {"lower_s": round(t1 - t, 2), "compile_s": round(t2 - t1, 2),
                 "run_s": round(t3 - t2, 3)}
    return result

solver = make_static_solver(scene.lattice, scene.supports, model=scene.model)
timed("static solver", jax.jit(lambda z: solver(z, scene.material, scene.loading, 0.0)), x)
start = static_equilibrium(scene, config)
forward = _split_objective(scene, config, None)[0]
inside = timed("forward, equilibrium solved inside", forward, x, None, None)
given = timed("forward, equilibrium given", forward, x, None, start)
out["value_rel_difference"] = abs(float(given[0]) / float(inside[0]) - 1.0)
print(json.dumps(out))
"""


# the default experiment as a new user first runs it (`simulate_scene` under the policy, static
# start included), public API only, so that it also runs from an older checkout (`--before`)
DEFAULT = """
import json, time
t = time.perf_counter()
from design_engine.physics.scenes import build_scene
from design_engine.solve.run import simulate_scene
scene = build_scene("precompression-24x18", nx=24, ny=16, strain=0.02)
t1 = time.perf_counter(); run = simulate_scene(scene); t2 = time.perf_counter()
again = simulate_scene(scene); t3 = time.perf_counter()
print(json.dumps({"import_s": round(t1 - t, 2), "first_s": round(t2 - t1, 2),
                  "second_s": round(t3 - t2, 2), "J": run.metrics["target_ke_mean_J"],
                  "solver": run.metrics["solver"]["solver"]}))
"""


def child_json(code: str, src: Path) -> dict:
    """Run `code` in a fresh process on the sources in `src`, compilation cache off; the JSON
    its last line of output prints."""
    env = dict(os.environ, METARIG_JAX_CACHE="", PYTHONPATH=str(src))
    run = subprocess.run([sys.executable, "-c", code], env=env, cwd=src, capture_output=True,
                         text=True)
    if run.returncode != 0:
        raise SystemExit(f"{src}: {run.stderr[-2000:]}")
    return json.loads(run.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", nargs="*", choices=sorted(SCENES), default=["small", "full"],
                   help="the scenes whose programs are timed (none: the default experiment only)")
    p.add_argument("--out", type=Path, default=ROOT / "benchmarks/results/bench_compile.json")
    p.add_argument("--before", type=Path, help="a checkout of an earlier commit: the default "
                   "experiment's first simulate_scene from it and from this one, one after the "
                   "other (key `default_experiment`)")
    p.add_argument("--repeats", type=int, default=1, help="with --before: the two sides this "
                   "many times, alternating (every pair in `default_experiment.runs`)")
    args = p.parse_args(argv)
    if args.repeats < 1:
        p.error(f"--repeats must be at least 1, got {args.repeats}")
    result = {"machine": describe(), "load_average_1min": {"before": os.getloadavg()[0]},
              "scenes": {}}
    for key in args.scenes:
        label, code = SCENES[key]
        print(f"{label} ...", flush=True)
        env = dict(os.environ, METARIG_JAX_CACHE="")
        run = subprocess.run([sys.executable, "-c", CHILD % code], env=env, cwd=ROOT,
                             capture_output=True, text=True)
        if run.returncode != 0:
            print(run.stderr[-2000:], file=sys.stderr)
            return 1
        result["scenes"][label] = json.loads(run.stdout.strip().splitlines()[-1])
        print(json.dumps(result["scenes"][label], indent=1), flush=True)
    if args.before is not None:
        runs = []
        for k in range(args.repeats):
            print(f"default experiment {k + 1}/{args.repeats}, before and after ...", flush=True)
            runs.append({"before": {"src": str(args.before), **child_json(DEFAULT, args.before)},
                         "after": child_json(DEFAULT, ROOT)})
        result["default_experiment"] = {
            "scene": "precompression-24x18 at 24x16, 2 % (static start + pulse)", **runs[0],
            **({"runs": runs} if len(runs) > 1 else {})}
        print(json.dumps(result["default_experiment"], indent=1), flush=True)
    result["load_average_1min"]["after"] = os.getloadavg()[0]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    print(f"-> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
