"""The policy's programs of a scene from this checkout against an earlier one (issue 26, "per-step
cost"): compile time and run time of the value, the fused value and gradient, and the design
loop's forward and reverse passes, on scenes that start in contact and on the focusing scene,
from this checkout and from `--before DIR` (a checkout of an earlier commit, `git worktree add
DIR REF`). Writes benchmarks/results/bench_programs.json (or --out).

    .venv/bin/python benchmarks/bench_programs.py --before DIR [--scenes small full focusing]
        [--programs value vg split] [--repeats 2] [--max-dt US ...] [--out FILE]

Each case runs in a fresh process with the compilation cache off, the two checkouts alternating
(before, after, before, after, ...) so that a change of load hits both. Each program starts
from the design's static equilibrium where the scene has one, as the design loop solves it:
lowering, XLA compilation and the best of three runs of the compiled program (`split`: the
forward pass, value and pullback, and the reverse pass, `run.split_gradient`); J of both
checkouts is recorded (they must agree), and with `split` the gradient's norm. The process's
peak memory (`maxrss_gb`) and the load average before and after are recorded. `--max-dt`:
the policy's configuration at the given fixed steps instead (the refined steps of deep
contact), each a case of its own.
"""

import argparse
import json
import os
from pathlib import Path

import bench_compile
from machine import describe

ROOT = Path(__file__).resolve().parent.parent
# bench_compile's scenes that start in contact, and the focusing scene from rest
SCENES = {**bench_compile.SCENES,
          "focusing": ("focusing-24x16 (the paper's 8.1 scene, from rest)",
                       'build_scene("focusing-24x16")')}
PROGRAMS = ("value", "vg", "split")

CHILD = """
import dataclasses, json, resource, time
import jax, numpy as np
from design_engine.physics.scenes import build_scene
from design_engine.solve import run as run_mod
from design_engine.solve.policy import choose_config

scene = %s
programs = %r
max_dt_us = %r
config = choose_config(scene).config
if max_dt_us is not None:  # the policy's fixed step, at another step
    config = dataclasses.replace(config, solver=dataclasses.replace(config.solver,
                                                                    max_dt=max_dt_us * 1e-3))
x = scene.design
start = (run_mod.static_equilibrium(scene, config, x) if scene.loading.is_static else None)
objective = run_mod._objective(scene, config, None)
out = {"config": run_mod.config_summary(config)}


def timed(fn, *args):
    t = time.perf_counter(); lowered = jax.jit(fn).lower(*args); t1 = time.perf_counter()
    compiled = lowered.compile(); t2 = time.perf_counter()
    runs = []
    for _ in range(3):
        t3 = time.perf_counter(); result = jax.block_until_ready(compiled(*args))
        runs.append(time.perf_counter() - t3)
    return result, {"lower_s": round(t1 - t, 2), "compile_s": round(t2 - t1, 2),
                    "run_s": round(min(runs), 4)}


if "value" in programs:
    result, row = timed(objective, x, None, start)
    out["value"] = {**row, "J": float(result[0])}
if "vg" in programs:
    result, row = timed(jax.value_and_grad(objective, has_aux=True), x, None, start)
    out["value and gradient"] = {**row, "J": float(result[0][0])}
if "split" in programs:
    forward, reverse = run_mod.split_gradient(objective)
    result, row = timed(forward, x, None, start)
    out["forward pass"] = {**row, "J": float(result[0])}
    grad, row = timed(reverse, result[2], np.ones_like(result[0]))
    out["reverse pass"] = {**row, "gradient_norm": float(np.linalg.norm(grad))}
out["maxrss_gb"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6, 2)
print(json.dumps(out))
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--before", type=Path, required=True,
                    help="a checkout of the earlier commit (git worktree add DIR REF)")
    ap.add_argument("--scenes", nargs="+", choices=list(SCENES), default=list(SCENES))
    ap.add_argument("--programs", nargs="+", choices=PROGRAMS, default=list(PROGRAMS))
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--max-dt", type=float, nargs="+", metavar="US",
                    help="solve at these fixed steps (us) instead of the policy's own (each "
                    "scene's results keyed `<scene> at <US> us`)")
    ap.add_argument("--out", type=Path,
                    default=ROOT / "benchmarks" / "results" / "bench_programs.json")
    args = ap.parse_args()
    if args.repeats < 1:
        ap.error(f"--repeats must be at least 1, got {args.repeats}")
    if not (args.before / "design_engine").is_dir():
        raise SystemExit(f"--before {args.before}: not a checkout of this project")
    sides = {"before": args.before.resolve(), "after": ROOT}
    result = {"before": str(args.before), "programs": args.programs, "machine": describe(),
              "scenes": {},
              "load_average_1min": {"before": round(os.getloadavg()[0], 2)}}
    cases = [(key, None) for key in args.scenes] if not args.max_dt else [
        (key, dt) for key in args.scenes for dt in args.max_dt]
    for key, dt in cases:
        label, code = SCENES[key]
        name = key if dt is None else f"{key} at {dt:g} us"
        rows = {side: [] for side in sides}
        for k in range(args.repeats):
            for side, checkout in sides.items():
                print(f"{name} {k + 1}/{args.repeats} {side} ...", flush=True)
                rows[side].append(bench_compile.child_json(
                    CHILD % (code, tuple(args.programs), dt), checkout))
        result["scenes"][name] = {"scene": label, "max_dt_us": dt, "runs": rows}
        args.out.write_text(json.dumps(result, indent=1) + "\n")
    result["load_average_1min"]["after"] = round(os.getloadavg()[0], 2)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    for key, entry in result["scenes"].items():
        for side, runs in entry["runs"].items():
            for prog in ("value", "value and gradient", "forward pass", "reverse pass"):
                if prog in runs[0]:
                    print(f"{key:16} {side:6} {prog:18} compile "
                          f"{', '.join(str(r[prog]['compile_s']) for r in runs)} s, run "
                          f"{', '.join(str(r[prog]['run_s']) for r in runs)} s")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
