"""The fourth-order step's value-and-gradient program, from this checkout and from an earlier
one, side by side: its first call (tracing and compilation included) and its second, on the
protection scene at 8 % (24x18, the focus-vs-protect run's scene in deep static contact), by
the policy's configuration there with the fourth order and 4 contact substeps (as the policy
took it when the results were written).

    git worktree add /tmp/before REF --detach
    .venv/bin/python benchmarks/bench_order4_program.py --before /tmp/before --repeats 2 \
        --name bench_order4_program_amd

Each call runs in a fresh process with an empty compilation cache of its own, the two sides
alternating `--repeats` times; J must agree between them (relative difference recorded).
Writes OUT/NAME.json (default benchmarks/results/bench_order4_program.json).
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from machine import describe, write_report

ROOT = Path(__file__).resolve().parent.parent

CHILD = """
import dataclasses, json, time
import jax
from design_engine.physics.scenes import build_scene
from design_engine.solve import run as run_mod
from design_engine.solve.policy import choose_config
scene = build_scene("protection-24x18", strain=0.08)
config = choose_config(scene).config
config = dataclasses.replace(config, solver=dataclasses.replace(
    config.solver, order=4, contact_substeps=4, refined=False))
value_and_grad = run_mod.make_objective(scene, config)[0]
t = time.perf_counter(); jax.block_until_ready(value_and_grad(scene.design))
first = time.perf_counter() - t
t = time.perf_counter(); (j, _), _ = jax.block_until_ready(value_and_grad(scene.design))
print(json.dumps({"first_s": first, "second_s": time.perf_counter() - t, "J": float(j)}))
"""


def run_side(source: Path) -> dict:
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, PYTHONPATH=str(source), METARIG_JAX_CACHE=cache)
        out = subprocess.run([sys.executable, "-c", CHILD], env=env, cwd=source,
                             capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--before", type=Path, required=True, help="a checkout of an earlier commit")
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--name", default="bench_order4_program")
    p.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results")
    args = p.parse_args(argv)
    if not (args.before / "design_engine").is_dir():
        p.error(f"{args.before} is not a checkout of this project")
    rows = {"before": [], "after": []}
    load = [os.getloadavg()[0]]
    for k in range(args.repeats):
        for side, source in (("before", args.before), ("after", ROOT)):
            rows[side].append(run_side(source.resolve()))
            r = rows[side][-1]
            print(f"{side} {k + 1}: first call {r['first_s']:.1f} s, second {r['second_s']:.2f} s",
                  flush=True)
    load.append(os.getloadavg()[0])
    j = rows["before"][0]["J"], rows["after"][0]["J"]
    report = {"machine": describe(), "load_1min": load, "before": str(args.before),
              "rows": rows, "J_rel_diff": abs(j[0] - j[1]) / abs(j[0])}
    path = write_report(args.out, args.name, report)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
