"""How large may the ligaments' step be when the contact forces are substepped? A sweep on
scenes that start in contact (a static pre-compression past the contact cutoff).

On such a scene the highest natural frequency at the start, omega_max, is the contact barrier's
at the deepest void, and today's step 0.6 x 2 / omega_max shrinks with it (down to Dopri8 when
it falls below a quarter of the first step). With multiple time stepping
(`FixedStepVerlet.contact_substeps`) the barrier only needs its substep h = dt / n to resolve
it; the step dt itself then needs to resolve the ligaments alone (omega_lig, the highest
frequency without the contact terms) and, as every impulse multiple-time-stepping scheme, to
stay clear of the resonance of the slow kicks with the fast oscillation (dt x omega_c near pi).

For each design and scene: omega_max with and without the contact terms at the static start,
the barrier's omega_c at its deepest void; then value-and-gradient of the scene's objective by
Verlet with contact (float64, remat) at outer steps dt whose dt x omega_c runs over
`--ratios` (dt capped at 0.6 x 2 / omega_lig), each with the fewest substeps n (powers of 2)
that bring (dt / n) x omega_c within `policy.CONTACT_STEP_LIMIT`; plus today's step; each
against Dopri8 at rtol 1e-10 / atol 1e-8: relative error of J, gradient cosine, the solve's
work-energy drift (the policy's a-posteriori check) and the wall time of a call (compiled).

    .venv/bin/python benchmarks/bench_outer_step.py --run runs/fvp-base --evals 5 12 20
    .venv/bin/python benchmarks/bench_outer_step.py --task focus-vs-protect --scenes strain_8pct

Writes OUT/bench_outer_step.json after every row (a rerun skips the rows it holds) and
OUT/bench_outer_step.png.
"""

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np

from machine import describe
from run_folder import run_designs

HERE = Path(__file__).resolve().parent
RATIOS = (1.0, 1.5, 2.0, 2.5, 3.0, 4.0, 6.0)
REF_RTOL, REF_ATOL = 1e-10, 1e-8


def designs(task, xs, evals) -> list[tuple[str, np.ndarray]]:
    """(label, full design x) to sweep: the task's start, and evaluations `evals` of a run
    folder's designs `xs` (`run_folder.run_designs`)."""
    return [("start", np.asarray(task.initial_design))] + [
        (f"eval {e}", task.embed(xs[e - 1])) for e in evals if 1 <= e <= len(xs)]


def frequencies(scene, x) -> dict:
    """omega_max (rad/ms) at the static start with and without the contact terms, omega_c."""
    from design_engine.solve import policy
    from design_engine.solve.run import prestressed_state

    sc = scene.with_design(np.asarray(x))
    state = prestressed_state(sc)
    full = policy.max_angular_frequency(sc, state=state)
    lig = policy.max_angular_frequency(sc, state=state, use_contact=False)
    margin = policy.static_void_margin(sc, state)
    inertia = float(np.min(sc.unit_inertias_kgm2())) * 1e9  # g mm^2, as `solve_health`'s
    wc = policy.contact_frequency(margin, sc.material, inertia, sc.model)
    return {"omega_max": full, "omega_lig": lig, "omega_c": wc, "void_margin_deg":
            math.degrees(margin), "scene": sc}


def solve(scene, config, x, repeats: int = 1):
    """(J, health scalars, grad, seconds of the fastest compiled call)."""
    import jax

    from design_engine.solve.run import make_objective

    vg, _ = make_objective(scene, config)
    (value, health), grad = vg(x)
    jax.block_until_ready(grad)
    best = math.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        (value, health), grad = vg(x)
        jax.block_until_ready(grad)
        best = min(best, time.perf_counter() - t0)
    # the health scalars (the objective's aux also holds the start state and the terms)
    return (float(value), {k: float(v) for k, v in health.items() if np.ndim(v) == 0},
            np.asarray(grad), best)


def substeps_for(dt: float, wc: float, limit: float) -> int:
    n = 1
    while dt / n * wc > limit:
        n *= 2
    return n


def sweep(label: str, name: str, scene, x, ratios, rows: list, save) -> None:
    import diffrax

    from design_engine.solve import policy
    from design_engine.solve.fixed_step import FixedStepVerlet
    from design_engine.solve.simulate import SolverConfig

    f = frequencies(scene, x)
    sc = f.pop("scene")
    wc, wl, wm = f["omega_c"], f["omega_lig"], f["omega_max"]
    print(f"{label} {name}: omega_max {wm / 2 / math.pi:.2f} kHz, without contact "
          f"{wl / 2 / math.pi:.2f} kHz, omega_c {wc / 2 / math.pi:.2f} kHz, deepest void "
          f"{f['void_margin_deg']:.3f} deg above the asymptote", flush=True)
    ref_cfg = SolverConfig(solver=diffrax.Dopri8(), rtol=REF_RTOL, atol=REF_ATOL,
                           max_steps=400_000)
    t0 = time.perf_counter()
    j_ref, _, g_ref, _ = solve(sc, ref_cfg, x, repeats=0)
    ref_s = time.perf_counter() - t0
    cap = policy.STABILITY_SAFETY * 2.0 / wl
    steps = [("today", policy.STABILITY_SAFETY * 2.0 / wm)]
    steps += [(f"{r:g}", min(r / wc, cap)) for r in ratios]
    seen = set()
    for tag, dt in steps:
        n = substeps_for(dt, wc, policy.CONTACT_STEP_LIMIT)
        key = (round(dt, 9), n)
        if key in seen:
            continue
        seen.add(key)
        cfg = SolverConfig(solver=FixedStepVerlet(max_dt=dt, remat=True, contact_substeps=n),
                           use_contact=True, dtype="float64")
        try:
            j, health, g, secs = solve(sc, cfg, x)
            err = abs(j - j_ref) / abs(j_ref)
            cos = float(g @ g_ref / (np.linalg.norm(g) * np.linalg.norm(g_ref)))
            drift, failed = health["energy_error"], None
        except Exception as exc:  # noqa: BLE001 - a diverged solve is a result of the sweep
            err, cos, drift, secs, failed = None, None, None, None, str(exc).splitlines()[0]
        rows.append({"design": label, "scene": name, "step": tag, "dt_us": dt * 1e3,
                     "substeps": n, "dt_omega_c": dt * wc, "dt_omega_lig": dt * wl,
                     "J_rel_err": err, "grad_cosine": cos, "energy_error": drift,
                     "call_s": secs, "failed": failed, "reference_s": ref_s,
                     **{k: v for k, v in f.items()}})
        print(f"  dt {dt * 1e3:6.2f} us ({tag}) x{n}: dt w_c {dt * wc:4.2f}, J error "
              f"{err if err is None else f'{err:.1e}'}, cosine {cos}, drift {drift}, "
              f"{secs if secs is None else f'{secs:.2f} s'}{' ' + failed if failed else ''}",
              flush=True)
        save()


def plot(rows: list, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4.2))
    groups = sorted({(r["design"], r["scene"]) for r in rows})
    for k, g in enumerate(groups):
        sel = [r for r in rows if (r["design"], r["scene"]) == g and r["failed"] is None]
        sel.sort(key=lambda r: r["dt_omega_c"])
        x = [r["dt_omega_c"] for r in sel]
        a.semilogy(x, [max(r["J_rel_err"], 1e-12) for r in sel], "o-", color=f"C{k}",
                   label=f"{g[0]}, {g[1]}")
        a.semilogy(x, [max(r["energy_error"], 1e-12) for r in sel], "x:", color=f"C{k}")
        b.plot(x, [r["call_s"] for r in sel], "o-", color=f"C{k}")
    a.axhline(1e-4, color="k", lw=0.6)
    a.axvline(math.pi, color="grey", lw=0.6)
    a.set_xlabel("dt x omega_c (outer step x the barrier's frequency)")
    a.set_ylabel("J relative error (o) / work-energy drift (x)")
    a.legend(fontsize=7)
    b.set_xlabel("dt x omega_c")
    b.set_ylabel("value and gradient, s (compiled)")
    fig.suptitle("Verlet with contact substeps against Dopri8 rtol 1e-10", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--task", default="focus-vs-protect")
    p.add_argument("--scenes", nargs="*", help="scenes of the task (default: all)")
    p.add_argument("--run", type=Path, help="a `metarig design` run folder of the task")
    p.add_argument("--evals", nargs="*", type=int, default=[], help="its evaluations to sweep")
    p.add_argument("--no-start", action="store_true", help="skip the task's start design")
    p.add_argument("--ratios", nargs="*", type=float, default=list(RATIOS))
    p.add_argument("--out", type=Path, default=Path("runs/bench-outer-step"))
    args = p.parse_args(argv)

    import jax

    jax.config.update("jax_enable_x64", True)
    from design_engine.design.task import load_task

    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "bench_outer_step.json"
    report = json.loads(path.read_text()) if path.exists() else {"rows": []}
    report.update(machine=describe(), task=args.task)
    rows = report["rows"]

    def save():
        path.write_text(json.dumps(report, indent=1))

    task, xs = (run_designs(p, args.task, args.run) if args.run is not None
                else (load_task(args.task), []))
    done = {(r["design"], r["scene"]) for r in rows}
    for label, x in designs(task, xs, args.evals):
        if args.no_start and label == "start":
            continue
        for name, scene in task.scenes.items():
            if (args.scenes and name not in args.scenes) or (label, name) in done:
                continue
            sweep(label, name, scene, x, args.ratios, rows, save)
    save()
    plot(rows, args.out / "bench_outer_step.png")
    print(f"-> {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
