"""The design loop's value and gradient as one program against a forward pass that returns its
pullback and a reverse pass that takes it (`TaskEvaluator._function`, which the policy driver
uses so that a rejected solve does not pay for its gradient: `solve_with_policy(finish=)`).

On one design of a `metarig design` run folder (default evaluation 5 of a focus-vs-protect run)
and one scene, with the configuration the policy chooses for it there (`policy.choose_config`)
and the design's own equilibrium given, as in a design run: wall time of the fused value and
gradient, of the forward pass and of the reverse pass, each compiled first and the best of
`--repeats` interleaved rounds, and the largest difference of the two gradients. Writes
OUT/bench_reverse_split.json.

    .venv/bin/python benchmarks/bench_reverse_split.py --run runs/fvp20 --eval 5 \
        --scene strain_8pct --out benchmarks/results
"""

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

from machine import describe
from run_folder import run_designs


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--task", default="focus-vs-protect")
    p.add_argument("--run", type=Path, required=True, help="a `metarig design` run folder")
    p.add_argument("--eval", type=int, default=5)
    p.add_argument("--scene", default="strain_8pct")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--out", type=Path, default=Path("runs/bench-reverse-split"))
    args = p.parse_args(argv)
    task, xs = run_designs(p, args.task, args.run, args.scene)
    if not 1 <= args.eval <= len(xs):
        p.error(f"--eval must be 1..{len(xs)}")
    import jax
    import jax.numpy as jnp

    from design_engine.design.evaluator import TaskEvaluator
    from design_engine.solve.policy import choose_config

    x = task.embed(xs[args.eval - 1])
    scene = task.scenes[args.scene]
    evaluator = TaskEvaluator(task)
    config = evaluator._budgeted(choose_config(scene.with_design(x)).config, args.scene)
    forward, reverse, objective = evaluator._function(args.scene, config)
    fused = jax.jit(jax.value_and_grad(objective, has_aux=True))  # the one program of before
    equilibrium = np.asarray(evaluator._equilibrium(args.scene, x)).reshape(-1)[
        np.asarray(scene.supports.free)]
    inputs = (jnp.asarray(x), scene.material, scene.loading, jnp.asarray(scene.sample_times),
              evaluator._weights(args.scene), None, jnp.asarray(equilibrium))

    def run_fused():
        return jax.block_until_ready(fused(*inputs))[1]

    def run_split():
        value, _, pullback = jax.block_until_ready(forward(*inputs))
        t = time.perf_counter()
        grad = jax.block_until_ready(reverse(pullback, jnp.ones_like(value)))
        return grad, time.perf_counter() - t

    g_fused, (g_split, _) = run_fused(), run_split()  # compiled before timing
    times = {"fused_s": [], "forward_s": [], "reverse_s": []}
    load0 = os.getloadavg()
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        run_fused()
        times["fused_s"].append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        _, reverse_s = run_split()
        times["forward_s"].append(time.perf_counter() - t0 - reverse_s)
        times["reverse_s"].append(reverse_s)
    report = {"task": args.task, "run": str(args.run), "eval": args.eval, "scene": args.scene,
              "config": repr(config), **{k: min(v) for k, v in times.items()},
              "all": times, "max_gradient_difference": float(np.max(np.abs(
                  np.asarray(g_fused) - np.asarray(g_split)))),
              "max_gradient": float(np.max(np.abs(np.asarray(g_fused)))),
              "machine": describe(), "load_average_start": load0,
              "load_average_end": os.getloadavg()}
    print(f"fused {report['fused_s']:.2f} s; forward {report['forward_s']:.2f} s + reverse "
          f"{report['reverse_s']:.2f} s; gradients differ by {report['max_gradient_difference']:.1e}"
          f" (largest {report['max_gradient']:.2g})")
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "bench_reverse_split.json").write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
