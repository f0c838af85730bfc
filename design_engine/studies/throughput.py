"""Batched throughput (`jax.vmap` over designs) and first-call compile time, cold and cached."""

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from design_engine.physics.scenes import build_scene
from design_engine.solve.run import default_choice
from design_engine.solve.simulate import make_simulator

_COMPILE_PROBE = """
import time, jax, jax.numpy as jnp
t0 = time.perf_counter()
import design_engine
from design_engine.physics.scenes import build_scene
from design_engine.solve.fixed_step import FixedStepVerlet
from design_engine.solve.run import make_objective
from design_engine.solve.simulate import SolverConfig
scene = build_scene("focusing-24x16")
vg, _ = make_objective(scene, SolverConfig(solver=FixedStepVerlet(max_dt={dt!r})))
jax.block_until_ready(vg(jnp.asarray(scene.design)))
print(time.perf_counter() - t0)
"""


def compile_times(dt_ms: float) -> dict:
    """First value-and-gradient call in a fresh process, with an empty and with a warm cache, s."""
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, METARIG_JAX_CACHE=cache)
        out = {}
        for label in ("cold_cache_s", "warm_cache_s"):
            r = subprocess.run([sys.executable, "-c", _COMPILE_PROBE.format(dt=dt_ms)], env=env,
                               capture_output=True, text=True, check=True)
            out[label] = float(r.stdout.strip().splitlines()[-1])
    return out


def batch_throughput(batch_sizes=(1, 2, 4, 8, 16), repeats: int = 2, seed: int = 0) -> list[dict]:
    """Forward cost per design of `vmap(simulate)` over perturbed 24x16 focusing designs."""
    scene = build_scene("focusing-24x16")
    config = default_choice(scene).config
    sim = make_simulator(scene.lattice, scene.supports, config, scene.sample_times,
                         model=scene.model)
    batched = jax.jit(jax.vmap(sim, in_axes=(0, None, None, None)))
    ts = jnp.asarray(scene.sample_times)
    rng = np.random.default_rng(seed)
    rows = []
    for b in batch_sizes:
        xs = jnp.asarray(scene.design[None] + rng.uniform(-0.1, 0.1, (b, scene.design.size)))
        t0 = time.perf_counter()
        jax.block_until_ready(batched(xs, scene.material, scene.loading, ts))
        first = time.perf_counter() - t0
        runs = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            sol = jax.block_until_ready(batched(xs, scene.material, scene.loading, ts))
            runs.append(time.perf_counter() - t0)
        assert bool(jnp.all(jnp.isfinite(sol.qdot)))
        t = float(np.median(runs))
        rows.append({"batch": b, "batch_s": t, "per_design_s": t / b,
                     "compile_s": max(first - t, 0.0)})
    return rows


def run_throughput(out: Path) -> dict:
    """Measure both, write out/throughput.json and out/throughput.png."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    scene = build_scene("focusing-24x16")
    rows = batch_throughput()
    report = {"scene": "focusing-24x16", "config": list(default_choice(scene).reasons),
              "device": str(jax.devices()[0]), "batches": rows,
              "value_and_grad_first_call": compile_times(default_choice(scene).config.solver.max_dt)}
    (out / "throughput.json").write_text(json.dumps(report, indent=2))
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.loglog([r["batch"] for r in rows], [r["per_design_s"] for r in rows], "o-")
    ax.set_xlabel("designs per vmap batch")
    ax.set_ylabel("forward wall time per design [s]")
    ax.set_title(f"focusing-24x16 forward, {report['device']}")
    ax.grid(alpha=0.3, which="both")
    fig.tight_layout()
    fig.savefig(out / "throughput.png", dpi=110)
    plt.close(fig)
    return report
