"""Where methods break: fixed step against the stability limit (explicit Verlet, and implicit
Newmark whose chord iterations stop converging instead), amplitude into the contact asymptote,
pre-compression; and on the contact scenes (`run_contact_stability`) the default policy against
a tight reference over strain up to 9 %, amplitude toward the barrier and fixed steps with
contact past the limit. Each failure must come back as a reported error, never as numbers.
"""

import json
from pathlib import Path

import numpy as np
from tqdm import tqdm

from design_engine.physics.scenes import build_scene
from design_engine.physics.statics import EquilibriumError, equilibrium_state
from design_engine.solve.fixed_step import FixedStepVerlet, is_fixed_step
from design_engine.solve.implicit_step import ImplicitNewmark
from design_engine.solve.policy import (contact_config, contact_frequency, max_angular_frequency,
                                        next_config, static_void_margin)
from design_engine.solve.run import simulate_scene
from design_engine.solve.simulate import SimulationError, SolverConfig, solve_health
from design_engine.studies.methods import reference_method


def _void_deg(margin_rad: float, scene) -> float:
    """A void angle (deg) from its margin above the contact asymptote (rad)."""
    return float(np.degrees(float(margin_rad) + float(scene.material.contact_min)))


def _outcome(scene, config) -> dict:
    try:
        run = simulate_scene(scene, config)
    except SimulationError as exc:
        return {"ok": False, "error": str(exc)}
    return {"ok": True, "J_mean_J": run.metrics["target_ke_mean_J"],
            "steps": run.metrics["solver"]["num_steps"],
            "min_void_deg": _void_deg(run.solution.min_void_margin, scene)}


def _policy_outcome(scene) -> dict:
    """The automatic policy's result (`simulate_scene(scene)`): J, steps, the configuration it
    ended with, how many solves it took and why."""
    try:
        run = simulate_scene(scene)
    except SimulationError as exc:
        return {"ok": False, "error": str(exc)}
    solver = run.metrics["solver"]
    why = solver["resolves"]
    return {"ok": True, "J_mean_J": run.metrics["target_ke_mean_J"], "steps": solver["num_steps"],
            "min_void_deg": _void_deg(run.solution.min_void_margin, scene),
            "config": f"{solver['solver']}{' + contact' if solver['use_contact'] else ''}, "
                      f"{solver['dtype']}",
            "solves": 1 + len(why), "wall_s": run.wall_s, "why": why}


def _static_start(scene) -> dict:
    """Where a static pre-compression starts: its smallest void (deg) and highest frequency (Hz),
    or the equilibrium's failure."""
    if not scene.loading.is_static:
        return {}
    try:
        state = equilibrium_state(scene)
    except EquilibriumError as exc:
        return {"equilibrium_error": str(exc)}
    margin = static_void_margin(scene, state)
    return {"static_min_void_deg": _void_deg(margin, scene),
            "static_omega_hz": max_angular_frequency(scene, state=state) / (2 * np.pi) * 1e3}


def _against_reference(scene) -> dict:
    """One row: the policy and the tight reference (Dopri8, rtol 1e-11, atol 1e-9) on `scene`."""
    row = _static_start(scene)
    row["policy"] = _policy_outcome(scene)
    row["reference"] = _outcome(scene, reference_method().config)
    if row["policy"]["ok"] and row["reference"]["ok"]:
        ref = row["reference"]["J_mean_J"]
        row["J_rel_err"] = abs(row["policy"]["J_mean_J"] - ref) / abs(ref)
    return row


def step_sweep_in_contact(scene, ratios, ref_j: float, state=None) -> list[dict]:
    """Fixed-step Verlet with contact (float64) at `ratios` x 2/omega_max (omega_max at the state
    the pulse starts from) on a scene in contact: per ratio the J error against `ref_j` (J), the
    barrier's dt x omega_c at the deepest void, and the policy's verdict on the result
    (`policy.next_config`: "accepted" or the configuration it re-solves with), or the reported
    failure."""
    limit = 2.0 / max_angular_frequency(scene, state=state)
    rows = []
    for r in tqdm(ratios, desc="contact dt / limit", leave=False):
        config = SolverConfig(solver=FixedStepVerlet(max_dt=r * limit), use_contact=True,
                              dtype="float64")
        row = {"dt_over_limit": r}
        try:
            run = simulate_scene(scene, config)
        except SimulationError as exc:
            rows.append(row | {"ok": False, "error": str(exc)})
            continue
        health = solve_health(run.solution, np)
        w_c = contact_frequency(float(health["void_margin"]), scene.material,
                                float(health["min_inertia"]), scene.model)
        nxt = next_config(config, health, scene)
        rows.append(row | {
            "ok": True, "J_mean_J": run.metrics["target_ke_mean_J"],
            "J_rel_err": abs(run.metrics["target_ke_mean_J"] - ref_j) / abs(ref_j),
            "dt_omega_c": r * limit * w_c, "energy_error": float(health["energy_error"]),
            "min_void_deg": _void_deg(health["void_margin"], scene),
            "verdict": _verdict(nxt)})
        if nxt is not None and is_fixed_step(nxt[0].solver):  # refined once: judged again
            rows[-1]["refined"] = _refined_row(scene, nxt[0], ref_j)
    return rows


def _verdict(nxt) -> str:
    """"accepted", "refined" (re-solved at a smaller fixed step) or the solver re-solved with."""
    if nxt is None:
        return "accepted"
    return "refined" if is_fixed_step(nxt[0].solver) else type(nxt[0].solver).__name__


def _refined_row(scene, config, ref_j: float) -> dict:
    """The policy's refined re-solve: its J error against `ref_j` and its own verdict."""
    try:
        run = simulate_scene(scene, config)
    except SimulationError as exc:
        return {"ok": False, "error": str(exc)}
    health = solve_health(run.solution, np)
    return {"ok": True, "dt_ms": config.solver.max_dt,
            "J_rel_err": abs(run.metrics["target_ke_mean_J"] - ref_j) / abs(ref_j),
            "energy_error": float(health["energy_error"]),
            "verdict": _verdict(next_config(config, health, scene))}


CONTACT_STRAINS = (0.0, 0.01, 0.03, 0.05, 0.07, 0.08, 0.09)
CONTACT_AMPLITUDES_M = (2.5e-3, 5e-3, 7.5e-3, 10e-3, 12.5e-3)
CONTACT_STEP_RATIOS = (0.2, 0.4, 0.6, 0.8, 1.0, 1.2)


def run_contact_stability(out: Path, *, nx: int = 24, ny: int = 18) -> dict:
    """The contact scenes (focus-vs-protect's 24x18, contact -10/-5 deg, static pre-compression;
    the mid-optimisation focusing design in contact): the default policy against the tight
    reference over strain 0-9 % and amplitude toward the barrier at 8 %, and fixed steps with
    contact past the limit. Writes out/stability_contact.json (after every part) and
    out/stability_contact.png."""
    from design_engine.studies.speedup import SCENES, term_scene

    out.mkdir(parents=True, exist_ok=True)
    path = out / "stability_contact.json"
    report: dict = {"scene": f"protection {nx}x{ny}, contact -10/-5 deg, static pre-compression",
                    "reference": "Dopri8, rtol 1e-11, atol 1e-9, with contact, float64"}

    def save():
        path.write_text(json.dumps(report, indent=2))

    rows = []
    for eps in tqdm(CONTACT_STRAINS, desc="strain (contact scenes)"):
        rows.append({"strain": eps} | _against_reference(
            build_scene("protection-24x18", nx=nx, ny=ny, strain=eps)))
        report["strain"] = {"amplitude_m": 7.5e-3, "rows": rows}
        save()
    rows = []
    for amp in tqdm(CONTACT_AMPLITUDES_M, desc="amplitude at 8 %"):
        rows.append({"amplitude_m": amp} | _against_reference(
            build_scene("protection-24x18", nx=nx, ny=ny, strain=0.08, amplitude_m=amp)))
        report["amplitude"] = {"strain": 0.08, "rows": rows}
        save()
    report["steps"] = {}
    fixture = term_scene(SCENES["focusing-contact-24x16"][0])
    for name, scene in ((f"protection {nx}x{ny} at 8 %",
                         build_scene("protection-24x18", nx=nx, ny=ny, strain=0.08)),
                        ("focusing-contact-24x16 (mid-optimisation design)", fixture)):
        state = equilibrium_state(scene) if scene.loading.is_static else None
        ref = _outcome(scene, reference_method().config)
        report["steps"][name] = {
            "reference_J": ref.get("J_mean_J"),
            "rows": step_sweep_in_contact(scene, CONTACT_STEP_RATIOS, ref["J_mean_J"], state)
            if ref["ok"] else [], "reference_error": ref.get("error")}
        save()
    _plot_contact(report, out / "stability_contact.png")
    return report


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


def _plot_contact(report: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.3))
    for ax, key, xkey, scale, xlabel in (
            (axes[0], "strain", "strain", 100.0, "pre-compression strain [%]"),
            (axes[1], "amplitude", "amplitude_m", 1e3, "input amplitude [mm] (8 % strain)")):
        rows = report.get(key, {}).get("rows", [])
        ok = [r for r in rows if "J_rel_err" in r]
        ax.semilogy([r[xkey] * scale for r in ok], [max(r["J_rel_err"], 1e-9) for r in ok], "o-",
                    color="b", label="default policy: J error vs reference")
        for r in rows:
            if "J_rel_err" not in r:
                ax.axvline(r[xkey] * scale, color="r", ls=":", lw=1)
            else:
                ax.annotate(r["policy"]["config"].split(",")[0].replace("FixedStep", ""),
                            (r[xkey] * scale, max(r["J_rel_err"], 1e-9)), fontsize=7,
                            textcoords="offset points", xytext=(3, 4))
        ax.plot([], [], ":", color="r", label="failure reported")
        ax.axhline(5e-3, color="k", ls="--", lw=0.8, label="0.5 %")
        ax.set_xlabel(xlabel)
        ax.set_ylabel("relative error of J")
        ax.set_title(report["scene"], fontsize=9)
        ax.legend(fontsize=8)
    ax = axes[2]
    for (name, part), colour in zip(report.get("steps", {}).items(), ("b", "g")):
        ok = [r for r in part["rows"] if r["ok"]]
        ax.loglog([r["dt_omega_c"] for r in ok], [max(r["J_rel_err"], 1e-9) for r in ok], "o-",
                  color=colour, label=name)
        for r in ok:
            if r["verdict"] != "accepted":
                ax.plot(r["dt_omega_c"], max(r["J_rel_err"], 1e-9), "x", color="r", ms=10)
    ax.plot([], [], "x", color="r", label="policy re-solves with Dopri8")
    failed = [f"{name.split(' (')[0]}: dt/limit {r['dt_over_limit']:g}"
              for name, part in report.get("steps", {}).items() for r in part["rows"] if not r["ok"]]
    if failed:
        ax.text(0.02, 0.02, "failure reported:\n" + "\n".join(failed), transform=ax.transAxes,
                fontsize=7, color="r", va="bottom")
    ax.axvline(1.0, color="k", ls="--", lw=0.8)
    ax.set_xlabel("dt x omega_c (barrier frequency at the deepest void)")
    ax.set_ylabel("relative error of J (Verlet + contact)")
    ax.set_title("fixed steps with contact toward the limit", fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
