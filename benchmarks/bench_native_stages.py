"""The native Verlet stages (one custom call a step, `physics.native.stages`) against the JAX
step around the native force, side by side in one run: value, and value and gradient, of the
policy's configuration on the scenes a design loop solves in contact.

    .venv/bin/python benchmarks/bench_native_stages.py --repeats 2 --name bench_native_stages_amd

Variants, each in a fresh process (its peak memory measured), taken in turn `--repeats` times:
- `jax`: the JAX step around the native force, recomputed in the reverse pass (the policy's
  `remat`), as before the native stages;
- `native`: the native stages, whose reverse pass reads the stage forces each forward step
  kept (what the engine runs).
`bench_native_stages_fvp13_amd.json` also holds `native-remat`, the native stages recomputed
in the reverse pass: measured at 6eecee7, the one commit that let a native step be recomputed
(this script there, with its third variant).

Scenes (`--scenes`): the focus-vs-protect task's 8 % and 1 % scenes and the focusing scene, at
the task's start or, with `--run DIR --eval K`, at evaluation K's design of a design run's
checkpoint (then name the scenes of its task).
Writes OUT/NAME.json (default benchmarks/results/bench_native_stages.json): per scene and
variant the times (s) of the second calls, J, and the gradient's relative difference and cosine
against `jax`'s.
"""

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
from machine import describe, write_report

ROOT = Path(__file__).resolve().parent.parent
VARIANTS = ("jax", "native")

CHILD = """
import json, resource, sys, time
import jax, numpy as np
import design_engine.solve.simulate as simulate
from design_engine.design.task import load_task
from design_engine.solve.policy import choose_config
from design_engine.solve.run import make_objective
variant, task_name, scene_name, run, k = sys.argv[1:6]
if variant == "jax":
    simulate.make_verlet_stages = lambda *a, **kw: None
task = load_task(task_name)
scene = task.scenes[scene_name]
if run:
    x = np.load(run + "/checkpoint.npz")["x"][int(k) - 1]
    scene = scene.with_design(task.embed(x))
config = choose_config(scene).config
value_and_grad, value = make_objective(scene, config)
x = jax.numpy.asarray(scene.design)
jax.block_until_ready(value(x)); jax.block_until_ready(value_and_grad(x))
fwd, vg = [], []
for _ in range(2):
    t = time.perf_counter(); jax.block_until_ready(value(x)); fwd.append(time.perf_counter() - t)
    t = time.perf_counter(); (j, aux), g = value_and_grad(x); jax.block_until_ready(g)
    vg.append(time.perf_counter() - t)
print(json.dumps({"value_s": fwd, "value_and_grad_s": vg, "J": float(j),
                  "steps": int(aux["num_steps"]) if "num_steps" in aux else None,
                  "solver": str(config.solver.summary()), "gradient": np.asarray(g).tolist(),
                  "peak_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6}))
"""

SCENES = ("focus-vs-protect/strain_8pct", "focus-vs-protect/strain_1pct", "focusing/pulse")


def child(variant: str, task: str, scene: str, run: str, k: int) -> dict:
    done = subprocess.run([sys.executable, "-c", CHILD, variant, task, scene, run, str(k)],
                          capture_output=True, text=True, cwd=ROOT)
    if done.returncode != 0:
        raise SystemExit(f"{variant} on {task}/{scene} failed: {done.stderr.strip()[-400:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--run", default="", help="a design run's folder (its checkpoint.npz)")
    ap.add_argument("--eval", type=int, default=1, help="which evaluation's design of --run")
    ap.add_argument("--scenes", nargs="+", default=SCENES, metavar="TASK/SCENE",
                    help="which scenes (with --run, those of its task)")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results"))
    ap.add_argument("--name", default="bench_native_stages")
    args = ap.parse_args()
    report = {"machine": describe(), "command": " ".join(sys.argv), "run": args.run,
              "eval": args.eval if args.run else None, "scenes": {}}
    for key in args.scenes:
        task_name, scene_name = key.split("/")
        rows = {v: [] for v in VARIANTS}
        for r in range(args.repeats):
            order = VARIANTS if r % 2 == 0 else VARIANTS[::-1]
            for v in order:
                rows[v].append(child(v, task_name, scene_name, args.run, args.eval))
                print(f"{key} {v}: value {min(rows[v][-1]['value_s']):.2f} s, value and "
                      f"gradient {min(rows[v][-1]['value_and_grad_s']):.2f} s, peak "
                      f"{rows[v][-1]['peak_rss_gb']:.2f} GB", flush=True)
        g_ref = np.asarray(rows["jax"][0]["gradient"])
        out = {}
        for v in VARIANTS:
            g = np.asarray(rows[v][0]["gradient"])
            out[v] = {
                "value_s": sorted(t for row in rows[v] for t in row["value_s"]),
                "value_and_grad_s": sorted(t for row in rows[v] for t in row["value_and_grad_s"]),
                "peak_rss_gb": [row["peak_rss_gb"] for row in rows[v]],
                "J": rows[v][0]["J"], "steps": rows[v][0]["steps"], "solver": rows[v][0]["solver"],
                "J_rel_diff_vs_jax": abs(rows[v][0]["J"] - rows["jax"][0]["J"])
                / abs(rows["jax"][0]["J"]),
                "grad_rel_diff_vs_jax": float(np.linalg.norm(g - g_ref) / np.linalg.norm(g_ref)),
                "grad_cosine_vs_jax": float(g @ g_ref / np.linalg.norm(g) / np.linalg.norm(g_ref)),
            }
        report["scenes"][key] = out
    path = write_report(Path(args.out), args.name, report)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
