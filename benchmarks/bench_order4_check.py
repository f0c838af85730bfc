"""The fourth-order step and its coarser check, against Verlet's half steps, on scenes whose
pulse starts in contact: the evidence behind `policy.CONTACT_ORDER`, `policy.COARSE`
and `policy.COARSE_CHECK_ORDER`.

For each design (evaluations `--evals` of a `metarig design` run folder of `--task`) and scene
(`--scene`, default the focus-vs-protect task's 8 % pre-compression), at the policy's step h
(`policy.choose_config` at that design, its contact substeps, float64), forward solves of J:
- Verlet at h/2 and h/4 (the steps the half-step check climbs down to);
- the fourth-order composition (`FixedStepVerlet(order=4)`) at 2h, 1.5h, h and h/2;
against Dopri8 at rtol 1e-10 / atol 1e-8. Per design: each J's relative error and wall time
(compiled first), the order-4 estimates of the error at h from the pair (h, 1.5h) taken as of
order 4 and of order 3 (the policy's), and from (h, 2h), each as a ratio to the true error;
the error growth from h to 1.5h (5.06 for a fourth order in its asymptotic range). With
`--gradients`, value and gradient by order 4 at h and Verlet at h/4 against Dopri8's: gradient
cosine, J error, wall time.

    .venv/bin/python benchmarks/bench_order4_check.py --run runs/bench-fvp-native/after \
        --evals 13 16 20 --gradients --name bench_order4_check_amd

Writes OUT/NAME.json (default benchmarks/results/bench_order4_check.json) after every design
(designs it holds are skipped on a rerun).
"""

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

from bench_step_convergence import TIGHT, _solve, _value_and_grad, against, policy_config
from machine import describe
from run_folder import add_run_arguments, run_designs

HERE = Path(__file__).resolve().parent


def at(config, order: int, factor: float):
    """`config` with the fixed step of `order` at `factor` x its step."""
    return dataclasses.replace(config, solver=dataclasses.replace(
        config.solver, order=order, max_dt=config.solver.max_dt * factor))


def forward_rows(scene, ref_j: float) -> list[dict]:
    from design_engine.solve.simulate import SimulationError

    base = policy_config(scene, "float64", 2)
    rows = []
    for order, factors in ((2, (0.5, 0.25)), (4, (2.0, 1.5, 1.0, 0.5))):
        for factor in factors:
            config = at(base, order, factor)
            row = {"order": order, "step_factor": factor, "dt_us": config.solver.max_dt * 1e3}
            try:
                j, health, wall = _solve(scene, config)
                row.update(J=j, J_rel_err=abs(j - ref_j) / abs(ref_j), wall_s=wall,
                           energy_error=health.get("energy_error"))
            except SimulationError as exc:
                row["error"] = str(exc)
            rows.append(row)
            print(f"  order {order} at {factor:g} h ({row['dt_us']:.1f} us): "
                  f"{row.get('J_rel_err', float('nan')):.2e} in "
                  f"{row.get('wall_s', float('nan')):.2f} s", flush=True)
    return rows


def estimates(rows: list[dict], ref_j: float) -> dict:
    """The order-4 estimates of the error at h, each against the true error."""
    from design_engine.solve.policy import COARSE, COARSE_CHECK_ORDER, relative_step_error

    j = {r["step_factor"]: r.get("J") for r in rows if r["order"] == 4}
    if any(j.get(f) is None for f in (1.0, 1.5, 2.0)):
        return {}
    true = abs(j[1.0] - ref_j) / abs(ref_j)
    coarse3 = relative_step_error(j[1.0], j[COARSE], COARSE, COARSE_CHECK_ORDER)
    coarse4 = relative_step_error(j[1.0], j[COARSE], COARSE, 4)
    double4 = relative_step_error(j[1.0], j[2.0], 2.0, 4)
    return {"true_error_at_h": true,
            "growth_h_to_coarse": abs(j[COARSE] - ref_j) / max(abs(j[1.0] - ref_j), 1e-300),
            "coarse_estimate_order3": coarse3, "coarse_estimate_order4": coarse4,
            "double_estimate_order4": double4,
            "ratio_coarse_order3": coarse3 / true, "ratio_coarse_order4": coarse4 / true,
            "ratio_double_order4": double4 / true}


def gradient_rows(scene) -> dict:
    import diffrax

    from design_engine.solve.simulate import SolverConfig

    ref_j, ref_g, ref_s, _ = _value_and_grad(scene, SolverConfig(
        solver=diffrax.Dopri8(), rtol=TIGHT[0], atol=TIGHT[1]))
    base = policy_config(scene, "float64", 2)
    out = {"reference_value_and_grad_s": ref_s}
    for label, config in (("order 4 at h", at(base, 4, 1.0)),
                          ("Verlet at h/4", at(base, 2, 0.25))):
        j, g, wall, _ = _value_and_grad(scene, config)
        out[label] = {**against(j, g, ref_j, ref_g), "value_and_grad_s": wall}
        print(f"  {label}: value and gradient cosine {out[label]['grad_cosine']:.7f} in "
              f"{wall:.1f} s", flush=True)
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_run_arguments(p, "strain_8pct")
    p.add_argument("--gradients", action="store_true")
    p.add_argument("--name", default="bench_order4_check")
    p.add_argument("--out", type=Path, default=HERE / "results")
    args = p.parse_args(argv)
    import diffrax

    from design_engine.solve.simulate import SolverConfig

    task, xs = run_designs(p, args.task, args.run, args.scene, args.evals)
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / f"{args.name}.json"
    doc = json.loads(path.read_text()) if path.exists() else {"designs": {}}
    doc.update(task=args.task, scene=args.scene, run=str(args.run), machine=describe())
    for e in args.evals:
        key = f"eval {e}"
        if key in doc["designs"]:
            continue
        print(f"{key} / {args.scene}", flush=True)
        scene = task.scenes[args.scene].with_design(task.embed(xs[e - 1]))
        t = time.perf_counter()
        ref_j, _, ref_s = _solve(scene, SolverConfig(solver=diffrax.Dopri8(), rtol=TIGHT[0],
                                                     atol=TIGHT[1]))
        rows = forward_rows(scene, ref_j)
        row = {"reference_J": ref_j, "reference_s": ref_s, "forward": rows,
               "estimates": estimates(rows, ref_j), "machine": describe()}
        if args.gradients:
            row["gradients"] = gradient_rows(scene)
        row["wall_s"] = time.perf_counter() - t
        doc["designs"][key] = row
        path.write_text(json.dumps(doc, indent=1) + "\n")
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
