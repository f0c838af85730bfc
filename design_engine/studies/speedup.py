"""Side-by-side speed-up: default configuration vs the reference-like baseline, one run, one machine."""

import json
import os
import platform
import statistics
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from design_engine.auto import choose_config
from design_engine.run import checked, make_objective
from design_engine.scenes import build_scene
from design_engine.studies.measure import errors
from design_engine.studies.methods import baseline_method, reference_method


def _median_vg(vg, x, config, repeats: int):
    t0 = time.perf_counter()
    res = checked(jax.block_until_ready(vg(x)), config)
    compile_s = time.perf_counter() - t0
    runs = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        res = checked(jax.block_until_ready(vg(x)), config)
        runs.append(time.perf_counter() - t0)
    med = statistics.median(runs)
    return med, max(compile_s - med, 0.0), float(res[0][0]), np.asarray(res[1], np.float64)


def run_speedup(out: Path, *, repeats: int = 3, baseline_repeats: int = 2, progress=print) -> dict:
    """Measure value-and-gradient of the 24x16 focusing objective with the baseline and the default
    configuration (medians, compile excluded) and their errors against a Dopri8 reference."""
    out.mkdir(parents=True, exist_ok=True)
    scene = build_scene("focusing-24x16")
    x = jnp.asarray(scene.design)
    choice = choose_config(scene)
    rows = {}
    for label, config, n in (("default", choice.config, repeats),
                             ("baseline", baseline_method().config, baseline_repeats)):
        progress(f"{label}: compiling and timing {n} value-and-gradient evaluations ...")
        vg, _ = make_objective(scene, config)
        rows[label] = _median_vg(vg, x, config, n)
    ref_path = out / "reference_focusing-24x16.npz"
    if ref_path.exists():
        with np.load(ref_path) as f:
            j_ref, g_ref = float(f["J"]), f["grad"]
    else:
        progress("reference: Dopri8, rtol 1e-11, atol 1e-9 ...")
        ref = reference_method().config
        vg, _ = make_objective(scene, ref)
        (j_ref, _), g_ref = checked(jax.block_until_ready(vg(x)), ref)
        j_ref, g_ref = float(j_ref), np.asarray(g_ref, np.float64)
        np.savez(ref_path, J=j_ref, grad=g_ref)
    d_err = errors(rows["default"][2], rows["default"][3], j_ref, g_ref)
    b_err = errors(rows["baseline"][2], rows["baseline"][3], j_ref, g_ref)
    report = {
        "scene": "focusing-24x16",
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count(),
                    "device": str(jax.devices()[0])},
        "baseline": "Dopri5, rtol 1e-8, atol 1e-4, BacksolveAdjoint, float64, full model",
        "default": list(choice.reasons),
        "baseline_s": rows["baseline"][0],
        "default_s": rows["default"][0],
        "ratio": rows["baseline"][0] / rows["default"][0],
        "baseline_compile_s": rows["baseline"][1],
        "default_compile_s": rows["default"][1],
        **d_err,
        "baseline_errors": b_err,
        "J_ref_mean_mJ": j_ref / scene.n_samples,
    }
    (out / "speedup.json").write_text(json.dumps(report, indent=2))
    return report
