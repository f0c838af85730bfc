"""Measure one method on one scene: J and dJ/dx, wall times, steps, compile time."""

import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np

from design_engine.physics.scenes import Scene
from design_engine.physics.statics import forget_equilibria
from design_engine.solve.run import checked, compiled_simulator, make_objective
from design_engine.solve.simulate import SolverConfig, check_solution
from design_engine.studies.methods import rhs_evaluations


def timed(fn, repeats: int):
    """(first call s, median of `repeats` more s, result); every call solves a static
    pre-compression anew (`forget_equilibria`), as a new design would."""
    forget_equilibria()
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn())
    first = time.perf_counter() - t0
    runs = []
    for _ in range(repeats):
        forget_equilibria()
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn())
        runs.append(time.perf_counter() - t0)
    return first, statistics.median(runs) if runs else first, out


def measure(scene: Scene, config: SolverConfig, *, grad: bool = True, repeats: int = 2) -> dict:
    """Forward and value-and-gradient of the scene objective with `config`.

    Returns a JSON-ready dict: J (mJ), forward_s, forward_compile_s, steps, rhs_evals, and with
    `grad`: value_and_grad_s, value_and_grad_compile_s and the gradient (numpy, under "_grad").
    Failures are returned as {"error": message}, never raised.
    """
    x = jnp.asarray(scene.design)
    out: dict = {}
    try:
        sim = compiled_simulator(scene, config)
        ts = jnp.asarray(scene.sample_times)
        first, fwd, sol = timed(lambda: sim(x, scene.material, scene.loading, ts), repeats)
        check_solution(sol, config)
        steps = int(sol.num_steps)
        out.update(forward_s=fwd, forward_compile_s=max(first - fwd, 0.0), steps=steps,
                   rhs_evals=rhs_evaluations(config, steps))
        if grad:
            vg, _ = make_objective(scene, config)
            first, t_vg, res = timed(lambda: vg(x), max(1, repeats - 1))
            checked(res, config)
            (j, _), g = res
            out.update(J=float(j), value_and_grad_s=t_vg,
                       value_and_grad_compile_s=max(first - t_vg, 0.0),
                       _grad=np.asarray(g, np.float64))
    except Exception as exc:  # noqa: BLE001 -- a failing method is a data point, not a crash
        out["error"] = f"{type(exc).__name__}: {exc}"
    return out


def errors(j: float, g: np.ndarray, j_ref: float, g_ref: np.ndarray) -> dict:
    """Relative error of J, relative error and cosine similarity of the gradient."""
    return {"J_rel_err": abs(j - j_ref) / abs(j_ref),
            "grad_rel_err": float(np.linalg.norm(g - g_ref) / np.linalg.norm(g_ref)),
            "grad_cosine": float(g @ g_ref / (np.linalg.norm(g) * np.linalg.norm(g_ref)))}
