"""Where methods break: fixed step against the stability limit (explicit Verlet, and implicit
Newmark whose chord iterations stop converging instead), amplitude into the contact asymptote,
pre-compression. Each failure must come back as a reported error, never as numbers.
"""

import json
from pathlib import Path

import numpy as np
from tqdm import tqdm

from design_engine.auto import contact_config, max_angular_frequency
from design_engine.fixed_step import FixedStepVerlet
from design_engine.implicit_step import ImplicitNewmark
from design_engine.run import simulate_scene
from design_engine.scenes import build_scene
from design_engine.simulate import SimulationError, SolverConfig


def _outcome(scene, config) -> dict:
    try:
        run = simulate_scene(scene, config)
    except SimulationError as exc:
        return {"ok": False, "error": str(exc)}
    return {"ok": True, "J_mean_J": run.metrics["target_ke_mean_J"],
            "steps": run.metrics["solver"]["num_steps"],
            "min_void_deg": float(np.degrees(float(run.solution.min_void_margin))
                                  + np.degrees(scene.material.contact_min))}


def run_stability(out: Path) -> dict:
    """Run the three sweeps; write out/stability.json and out/stability.png."""
    out.mkdir(parents=True, exist_ok=True)
    report: dict = {}
    # 1. fixed step against the stability limit 2 / omega_max (focusing, 12x8, 4 mm pulse)
    scene = build_scene("focusing-24x16", nx=12, ny=8, amplitude_m=4e-3)
    limit = 2.0 / max_angular_frequency(scene)
    ref = _outcome(scene, SolverConfig(rtol=1e-10, atol=1e-9))["J_mean_J"]

    def step_sweep(scheme, ratios, desc):
        rows = []
        for r in tqdm(ratios, desc=desc):
            o = _outcome(scene, SolverConfig(solver=scheme(r * limit)))
            o["dt_over_limit"] = r
            if o["ok"]:
                o["J_rel_err"] = abs(o["J_mean_J"] - ref) / ref
            rows.append(o)
        return rows

    rows = step_sweep(lambda dt: FixedStepVerlet(max_dt=dt),
                      (0.2, 0.4, 0.6, 0.8, 0.9, 0.95, 1.0, 1.05, 1.2), "dt / limit")
    implicit = step_sweep(lambda dt: ImplicitNewmark(max_dt=dt, iterations=3),
                          (0.6, 1.2, 2.0, 3.0, 4.0), "implicit dt / limit")
    report["step_vs_limit"] = {"scene": "focusing 12x8, 4 mm", "limit_ms": limit, "rows": rows,
                               "newmark_rows": implicit}
    # 2. amplitude into the contact asymptote (44 deg bias: voids of 2 deg), fixed step vs Dopri8
    rows = []
    for amp in tqdm((2e-3, 4e-3, 6e-3, 8e-3, 1e-2), desc="amplitude"):
        sc = build_scene("focusing-24x16", nx=8, ny=6, bias_angle_deg=44.0, amplitude_m=amp)
        dt = 0.6 * 2.0 / max_angular_frequency(sc)
        rows.append({"amplitude_m": amp,
                     "verlet": _outcome(sc, SolverConfig(solver=FixedStepVerlet(max_dt=dt))),
                     "dopri8": _outcome(sc, contact_config())})
    report["amplitude"] = {"scene": "focusing 8x6, bias 44 deg", "rows": rows,
                           "contact_deg": [-15.0, -10.0]}
    # 3. pre-compression: fixed step chosen at rest vs Dopri8
    rows = []
    base = build_scene("protection-24x18", nx=8, ny=8, strain=0.0)
    dt_rest = 0.6 * 2.0 / max_angular_frequency(base)
    for eps in tqdm((0.01, 0.03, 0.05, 0.08), desc="strain"):
        sc = build_scene("protection-24x18", nx=8, ny=8, strain=eps)
        rows.append({"strain": eps,
                     "verlet": _outcome(sc, SolverConfig(solver=FixedStepVerlet(max_dt=dt_rest))),
                     "dopri8": _outcome(sc, contact_config())})
    report["precompression"] = {"scene": "protection 8x8", "verlet_dt_ms": dt_rest, "rows": rows,
                                "contact_deg": [-10.0, -5.0]}
    (out / "stability.json").write_text(json.dumps(report, indent=2))
    _plot(report, out / "stability.png")
    return report


def _plot(report: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.3))
    ax = axes[0]
    for key, style, colour, label in (("rows", "o-", "r", "Verlet"),
                                      ("newmark_rows", "s--", "m", "Newmark (implicit, 3 chord it.)")):
        rows = report["step_vs_limit"].get(key, [])
        ok = [r for r in rows if r["ok"]]
        ax.semilogy([r["dt_over_limit"] for r in ok], [max(r["J_rel_err"], 1e-9) for r in ok],
                    style, label=f"{label}: J error")
        for r in rows:
            if not r["ok"]:
                ax.axvline(r["dt_over_limit"], color=colour, ls=":", lw=1)
        ax.plot([], [], ":", color=colour, label=f"{label}: failure reported")
    ax.set_xlabel("fixed step / (2 / omega_max)")
    ax.set_ylabel("relative error of J")
    ax.set_title(report["step_vs_limit"]["scene"])
    ax.legend(fontsize=8)
    for ax, key, xkey, xlabel in ((axes[1], "amplitude", "amplitude_m", "input amplitude [m]"),
                                  (axes[2], "precompression", "strain", "pre-compression strain")):
        rs = report[key]["rows"]
        asymptote, cutoff = report[key]["contact_deg"]
        for m, style in (("verlet", "o"), ("dopri8", "s")):
            for r in rs:
                o = r[m]
                ax.plot(r[xkey], o["min_void_deg"] if o["ok"] else asymptote - 5.0,
                        style, color="g" if o["ok"] else "r", ms=8, fillstyle="none" if m == "verlet" else "full")
        ax.axhline(cutoff, color="k", ls="--", lw=0.8)
        ax.axhline(asymptote, color="k", ls="-", lw=0.8)
        ax.set_xlabel(xlabel)
        ax.set_ylabel("smallest void angle [deg] (red: failure reported)")
        ax.set_title(f"{report[key]['scene']}: open = Verlet, filled = Dopri8")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
