"""The design loop's value and gradient as one program against a forward pass that returns its
pullback and a reverse pass that takes it (`TaskEvaluator._function`, which the policy driver
uses so that a rejected solve does not pay for its gradient: `solve_with_policy(finish=)`).

On one design of a `metarig design` run folder (default evaluation 5 of a focus-vs-protect run)
and one scene, with the configuration the policy chooses for it there (`policy.choose_config`)
and the design's own equilibrium given, as in a design run: wall time of the fused value and
gradient, of the forward pass and of the reverse pass, each compiled first and the best of
`--repeats` interleaved rounds, and the largest difference of the two gradients. With
`--solver dopri8` the scene is solved as the policy's adaptive fallback solves it for a
gradient (`policy.for_gradient`: one stored state per step, up to its memory bound), and the
reverse pass with diffrax's default checkpointing (log(max_steps) stored states) is timed
beside it. Writes OUT/bench_reverse_split.json (OUT/bench_reverse_split_dopri8_evalN.json).

    .venv/bin/python benchmarks/bench_reverse_split.py --run runs/fvp20 --eval 5 \
        --scene strain_8pct --out benchmarks/results [--solver dopri8]
"""

import argparse
import dataclasses
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
    p.add_argument("--solver", choices=("policy", "dopri8"), default="policy",
                   help="the policy's choice for the design (default) or its Dopri8 fallback")
    p.add_argument("--out", type=Path, default=Path("runs/bench-reverse-split"))
    args = p.parse_args(argv)
    task, xs = run_designs(p, args.task, args.run, args.scene)
    if not 1 <= args.eval <= len(xs):
        p.error(f"--eval must be 1..{len(xs)}")
    import jax
    import jax.numpy as jnp

    from design_engine.design.evaluator import TaskEvaluator
    from design_engine.solve.policy import choose_config, contact_config

    x = task.embed(xs[args.eval - 1])
    scene = task.scenes[args.scene]
    evaluator = TaskEvaluator(task)
    chosen = (contact_config() if args.solver == "dopri8"
              else choose_config(scene.with_design(x)).config)
    config = evaluator._budgeted(chosen, args.scene)
    forward, reverse, objective = evaluator._function(args.scene, config)[:3]
    # the reverse pass with diffrax's default checkpointing (adaptive solves only)
    default = (evaluator._function(args.scene, dataclasses.replace(
        config, adjoint=type(config.adjoint)())) if args.solver == "dopri8" else None)
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

    def run_default():
        value, _, pullback = jax.block_until_ready(default[0](*inputs))
        t = time.perf_counter()
        grad = jax.block_until_ready(default[1](pullback, jnp.ones_like(value)))
        return grad, time.perf_counter() - t

    g_fused, (g_split, _) = run_fused(), run_split()  # compiled before timing
    g_default = run_default()[0] if default else None
    times = {"fused_s": [], "forward_s": [], "reverse_s": []}
    if default:
        times["reverse_default_checkpoints_s"] = []
    load0 = os.getloadavg()
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        run_fused()
        times["fused_s"].append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        _, reverse_s = run_split()
        times["forward_s"].append(time.perf_counter() - t0 - reverse_s)
        times["reverse_s"].append(reverse_s)
        if default:
            times["reverse_default_checkpoints_s"].append(run_default()[1])
    steps = int(forward(*inputs)[1]["num_steps"])
    report = {"task": args.task, "run": str(args.run), "eval": args.eval, "scene": args.scene,
              "config": repr(config), "num_steps": steps, **{k: min(v) for k, v in times.items()},
              "all": times, "max_gradient_difference": float(np.max(np.abs(
                  np.asarray(g_fused) - np.asarray(g_split)))),
              "max_gradient": float(np.max(np.abs(np.asarray(g_fused)))),
              **({"max_gradient_difference_default_checkpoints": float(np.max(np.abs(
                  np.asarray(g_default) - np.asarray(g_split))))} if default else {}),
              "machine": describe(), "load_average_start": load0,
              "load_average_end": os.getloadavg()}
    print(f"fused {report['fused_s']:.2f} s; forward {report['forward_s']:.2f} s + reverse "
          f"{report['reverse_s']:.2f} s; gradients differ by {report['max_gradient_difference']:.1e}"
          f" (largest {report['max_gradient']:.2g})")
    if default:
        print(f"reverse with the default checkpointing: "
              f"{report['reverse_default_checkpoints_s']:.2f} s; gradients differ by "
              f"{report['max_gradient_difference_default_checkpoints']:.1e}")
    args.out.mkdir(parents=True, exist_ok=True)
    name = "bench_reverse_split" + (f"_dopri8_eval{args.eval}" if default else "") + ".json"
    (args.out / name).write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
