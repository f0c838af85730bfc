"""Static pre-compression on the 24x18 protection scene: wall time of the equilibrium and of its
value and gradient (a functional of the equilibrium), at 1 % and 8 %, first call (compile
included) and warm. Writes benchmarks/results/bench_statics.json.

    .venv/bin/python benchmarks/bench_statics.py [strain ...]
"""

import json
import os
import platform
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from design_engine import build_scene
from design_engine.statics import make_static_solver

OUT = Path(__file__).resolve().parent / "results" / "bench_statics.json"


def timed(fn, *args):
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    return out, time.perf_counter() - t0


def main(argv):
    strains = [float(v) for v in argv] or [0.01, 0.08]
    rows = {}
    load0 = os.getloadavg()
    for strain in strains:
        s = build_scene("protection-24x18", strain=strain)
        ld, x = s.loading, jnp.asarray(s.design)
        eq = make_static_solver(s.lattice, s.supports)
        w = jnp.asarray(np.random.default_rng(0).normal(size=s.supports.free.size))
        solve = jax.jit(lambda x: eq(x, s.material, ld, ld.precompression_time))
        vg = jax.jit(jax.value_and_grad(
            lambda x: jnp.dot(eq(x, s.material, ld, ld.precompression_time)[0], w)))
        (_, info), first = timed(solve, x)
        _, warm = timed(solve, x)
        _, vg_first = timed(vg, x)
        _, vg_warm = timed(vg, x)
        rows[f"{strain:g}"] = {"n_free": int(s.supports.free.size),
                               "ramp_ms": ld.precompression_time,
                               "solve_first_s": first, "solve_s": warm,
                               "value_and_grad_first_s": vg_first, "value_and_grad_s": vg_warm,
                               "gradient_norm": float(info["gradient_norm"]),
                               "energy_mJ": float(info["energy"])}
        print(strain, rows[f"{strain:g}"], flush=True)
    doc = {"scene": "protection-24x18", "strains": rows,
           "machine": {"cpus": os.cpu_count(), "platform": platform.platform(),
                       "load_before": load0, "load_after": os.getloadavg()}}
    OUT.write_text(json.dumps(doc, indent=2) + "\n")


if __name__ == "__main__":
    main(sys.argv[1:])
