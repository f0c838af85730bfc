"""Side-by-side speed-up: default configuration vs the reference-like baseline, one run, one machine.

A study scene is one or more weighted objective terms, each a scene of `build_scene`; the
objective is sum_k w_k J_k (J_k the target energy summed over the samples, mJ) and its gradient
with respect to the (shared) design. The baseline is our engine configured as the published
code: Dopri5 at the spec tolerances, backsolve adjoint, float64, the full model, and the dynamic
pre-compression ramp. The default is the automatic policy (`run.make_objective(scene)`, with its
re-solves) on the default model (static pre-compression). Errors are measured against a tight
reference of the default's own model (Dopri8, rtol 1e-11, atol 1e-9), and the baseline's against
the same (for pre-compressed scenes that includes the ramp's residual motion, a model difference).
"""

import json
import os
import platform
import zlib
from dataclasses import dataclass
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from design_engine.physics.scenes import build_scene
from design_engine.solve.run import checked, default_choice, make_objective
from design_engine.studies.measure import errors, timed
from design_engine.studies.methods import baseline_method, reference_method
from metarig.readback import read_npz

FIXTURES = Path(__file__).resolve().parent / "fixtures"


@dataclass(frozen=True)
class Term:
    """One weighted objective term: `build_scene` keyword arguments and its weight."""

    scene: dict
    weight: float = 1.0
    design: str | None = None  # a design file in FIXTURES replacing the periodic design


# name -> terms. focusing-contact-24x16 is evaluation 60 of an MMA focusing run on 24x16 (its
# voids reach 90 % of the contact barrier's depth under the pulse); focus-vs-protect-24x18 is
# the two-strain evaluation of that task (spec 8.5, weights 0.75 / -0.25), reprogram-location
# the 2 % / 5 % pair of spec 8.4 (0.5 / 0.5).
SCENES: dict[str, tuple[Term, ...]] = {
    "focusing-24x16": (Term(dict(name="focusing-24x16")),),
    "focusing-contact-24x16": (Term(dict(name="focusing-24x16"),
                                    design="focusing-contact-24x16.json"),),
    "precompressed-contact-12x10": (Term(dict(name="protection-24x18", nx=12, ny=10,
                                              strain=0.05)),),
    "focus-vs-protect-24x18": (Term(dict(name="protection-24x18", strain=0.01), 0.75),
                               Term(dict(name="protection-24x18", strain=0.08), -0.25)),
    "reprogram-location-24x18": (
        Term(dict(name="precompression-24x18", strain=0.02,
                  target_windows={"upper": ((2, 2), (2, 4))}), 0.5),
        Term(dict(name="precompression-24x18", strain=0.05,
                  target_windows={"lower": ((2, 2), (2, -4))}), 0.5)),
}
BASELINE = "Dopri5, rtol 1e-8, atol 1e-4, BacksolveAdjoint, float64, full model, dynamic ramp"


def term_scene(term: Term, precompression: str = "static"):
    """The scene of one term (SI overrides as `build_scene` takes them)."""
    kw = dict(term.scene)
    if kw.get("strain"):
        kw["precompression"] = precompression
    scene = build_scene(kw.pop("name"), **kw)
    if term.design is not None:
        from design_engine.design.design_io import load_design

        _, x = load_design(FIXTURES / term.design)
        scene = scene.with_design(x)
    return scene


def timed_value_and_grad(vg, x, config, repeats: int):
    """(median s, compile s, J, grad) of `repeats` warm calls after one compiling call, each
    checked (`measure.timed`: every call solves a static pre-compression anew)."""
    first, med, res = timed(lambda: checked(jax.block_until_ready(vg(x)), config), repeats)
    return med, max(first - med, 0.0), float(res[0][0]), np.asarray(res[1], np.float64)


def _reference(name: str, scenes, out: Path, progress):
    """Tight reference J_k and grad_k of every term (cached in out/ per scene and design)."""
    path = out / f"reference_{name}.npz"
    stamp = np.asarray([zlib.crc32(s.design.tobytes()) for s in scenes] +
                       [int(s.loading.is_static) for s in scenes])
    if path.exists():
        f = read_npz(path, ("J", "grad"), "reference solution cache",
                     "remove it to compute it again", optional=("stamp",))
        if "stamp" in f and np.array_equal(f["stamp"], stamp):
            return list(f["J"]), list(f["grad"])
    config = reference_method().config
    js, gs = [], []
    for k, s in enumerate(scenes):
        progress(f"reference {k + 1}/{len(scenes)}: Dopri8, rtol 1e-11, atol 1e-9 ...")
        vg, _ = make_objective(s, config)
        (j, _), g = checked(jax.block_until_ready(vg(jnp.asarray(s.design))), config)
        js.append(float(j))
        gs.append(np.asarray(g, np.float64))
    np.savez(path, J=np.asarray(js), grad=np.asarray(gs), stamp=stamp)
    return js, gs


def run_speedup(out: Path, *, scene: str = "focusing-24x16", repeats: int = 3,
                baseline_repeats: int = 2, progress=print) -> dict:
    """Measure value-and-gradient of a study scene's objective with the baseline and the default
    configuration (medians, compile excluded) side by side, and their errors against a tight
    reference of the default's model. Writes out/speedup.json (focusing-24x16) or
    out/speedup_<scene>.json."""
    if scene not in SCENES:
        raise ValueError(f"unknown scene {scene!r}; choose one of: {', '.join(SCENES)}")
    out.mkdir(parents=True, exist_ok=True)
    terms = SCENES[scene]
    load0 = os.getloadavg()
    defaults = [term_scene(t) for t in terms]
    baselines = [term_scene(t, "ramp") for t in terms]
    base_cfg = baseline_method().config
    rows = []
    for k, (t, sd, sb) in enumerate(zip(terms, defaults, baselines)):
        tag = f"term {k + 1}/{len(terms)}"
        progress(f"{tag}: default configuration, {repeats} value-and-gradient evaluations ...")
        choice = default_choice(sd)
        vg, _ = make_objective(sd)
        d = timed_value_and_grad(vg, jnp.asarray(sd.design), None, repeats)
        progress(f"{tag}: baseline, {baseline_repeats} value-and-gradient evaluations ...")
        vg, _ = make_objective(sb, base_cfg)
        b = timed_value_and_grad(vg, jnp.asarray(sb.design), base_cfg, baseline_repeats)
        rows.append({"scene": t.scene, "weight": t.weight, "default_s": d[0],
                     "default_compile_s": d[1], "baseline_s": b[0], "baseline_compile_s": b[1],
                     "ratio": b[0] / d[0], "default": list(choice.reasons), "_d": d, "_b": b})
    j_ref, g_ref = _reference(scene, defaults, out, progress)
    w = [t.weight for t in terms]

    def combine(key):
        return (sum(wk * r[key][2] for wk, r in zip(w, rows)),
                sum(wk * r[key][3] for wk, r in zip(w, rows)))

    jr, gr = sum(wk * j for wk, j in zip(w, j_ref)), sum(wk * g for wk, g in zip(w, g_ref))
    jd, gd = combine("_d")
    jb, gb = combine("_b")
    for r, j, g in zip(rows, j_ref, g_ref):
        r["errors"] = errors(r["_d"][2], r["_d"][3], j, g)
        r["baseline_errors"] = errors(r["_b"][2], r["_b"][3], j, g)
        del r["_d"], r["_b"]
    n_t = defaults[0].n_samples
    report = {
        "scene": scene,
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count(),
                    "device": str(jax.devices()[0]), "load_before": load0,
                    "load_after": os.getloadavg()},
        "baseline": BASELINE,
        "default": rows[0]["default"] if len(rows) == 1 else [r["default"] for r in rows],
        "baseline_s": sum(r["baseline_s"] for r in rows),
        "default_s": sum(r["default_s"] for r in rows),
        "ratio": sum(r["baseline_s"] for r in rows) / sum(r["default_s"] for r in rows),
        "baseline_compile_s": sum(r["baseline_compile_s"] for r in rows),
        "default_compile_s": sum(r["default_compile_s"] for r in rows),
        **errors(jd, gd, jr, gr),
        "baseline_errors": errors(jb, gb, jr, gr),
        "J_ref_mean_mJ": jr / n_t,
        "terms": rows,
    }
    name = "speedup.json" if scene == "focusing-24x16" else f"speedup_{scene}.json"
    (out / name).write_text(json.dumps(report, indent=2))
    return report
