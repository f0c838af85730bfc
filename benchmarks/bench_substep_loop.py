"""The contact substeps of a fixed step as a loop against unrolled (issue 26, "per-step cost"):
compile time and run time of the policy's programs on scenes that start in contact, from this
checkout and from `--before DIR` (a checkout of an earlier commit, `git worktree add DIR REF`).
Writes benchmarks/results/bench_substep_loop.json.

    .venv/bin/python benchmarks/bench_substep_loop.py --before DIR [--scenes small full]
                                                      [--repeats 2] [--out FILE]

Each case runs in a fresh process with the compilation cache off, the two checkouts alternating
(before, after, before, after, ...) so that a change of load hits both. Per program (the value,
and the fused value and gradient, each from the design's static equilibrium, as the design loop
solves them): lowering, XLA compilation and the best of three runs of the compiled program; J
of both checkouts is recorded (they must agree). The load average is recorded before and after.
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
import jax
from design_engine.physics.scenes import build_scene
from design_engine.solve import run as run_mod
from design_engine.solve.policy import choose_config

scene = %s
config = choose_config(scene).config
x = scene.design
start = run_mod.static_equilibrium(scene, config, x)
objective = run_mod._objective(scene, config, None)
out = {"config": run_mod.config_summary(config)}
for name, fn in (("value", objective),
                 ("value and gradient", jax.value_and_grad(objective, has_aux=True))):
    t = time.perf_counter(); lowered = jax.jit(fn).lower(x, None, start); t1 = time.perf_counter()
    compiled = lowered.compile(); t2 = time.perf_counter()
    runs = []
    for _ in range(3):
        t3 = time.perf_counter(); result = jax.block_until_ready(compiled(x, None, start))
        runs.append(time.perf_counter() - t3)
    value = result[0][0] if name != "value" else result[0]
    out[name] = {"lower_s": round(t1 - t, 2), "compile_s": round(t2 - t1, 2),
                 "run_s": round(min(runs), 4), "J": float(value)}
print(json.dumps(out))
"""


def run_case(checkout: Path, scene_code: str) -> dict:
    env = {**os.environ, "JAX_ENABLE_COMPILATION_CACHE": "false", "PYTHONPATH": str(checkout)}
    proc = subprocess.run([sys.executable, "-c", CHILD % scene_code], cwd=checkout, env=env,
                          capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"{checkout}: {proc.stderr.strip().splitlines()[-1]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--before", type=Path, required=True,
                    help="a checkout of the earlier commit (git worktree add DIR REF)")
    ap.add_argument("--scenes", nargs="+", choices=sorted(SCENES), default=["small", "full"])
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--out", type=Path,
                    default=ROOT / "benchmarks" / "results" / "bench_substep_loop.json")
    args = ap.parse_args()
    if not (args.before / "design_engine").is_dir():
        raise SystemExit(f"--before {args.before}: not a checkout of this project")
    sides = {"before (substeps unrolled)": args.before.resolve(), "after (a loop)": ROOT}
    result = {"before": str(args.before), "machine": describe(), "scenes": {},
              "load_average_1min": {"before": round(os.getloadavg()[0], 2)}}
    for key in args.scenes:
        label, code = SCENES[key]
        rows = {side: [] for side in sides}
        for k in range(args.repeats):
            for side, checkout in sides.items():
                print(f"{key} {k + 1}/{args.repeats} {side} ...", flush=True)
                rows[side].append(run_case(checkout, code))
        result["scenes"][key] = {"scene": label, "runs": rows}
        args.out.write_text(json.dumps(result, indent=1) + "\n")
    result["load_average_1min"]["after"] = round(os.getloadavg()[0], 2)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    for key, entry in result["scenes"].items():
        for side, runs in entry["runs"].items():
            for prog in ("value", "value and gradient"):
                print(f"{key:5} {side:28} {prog:18} compile "
                      f"{', '.join(str(r[prog]['compile_s']) for r in runs)} s, run "
                      f"{', '.join(str(r[prog]['run_s']) for r in runs)} s")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
