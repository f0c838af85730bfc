"""The fourth-order step's contact substeps and step, by value and gradient: what the fourth
order costs and buys against Verlet, where contact is entered under the pulse and where the
pulse starts in contact (`policy.CONTACT_ORDER`, `policy.CONTACT_ENTRY_SUBSTEPS`).

For each design (evaluations `--evals` of a `metarig design` run folder of `--task`) and scene
`--scene`, the policy's own configuration at that design (`policy.choose_config`, its precision,
contact on) solves value and gradient by the fourth-order composition of Verlet steps
(`FixedStepVerlet(order=4)`) at each of `--factors` x the policy's step h with each of
`--substeps` contact substeps (in `--dtype` where given), and by Verlet at h with 4 contact
substeps (the policy's configuration with contact before it took the fourth order), against
Dopri8 at rtol 1e-10 / atol 1e-8. Per row: J's relative error, the gradient's cosine and relative error, and the value
and gradient's wall time (compiled first), the work-energy drift and h x omega_c of the contact
forces' step (`policy.contact_step_ratio`).

    .venv/bin/python benchmarks/bench_order4_substeps.py --run runs/bench-fvp-order4c/after \
        --scene strain_1pct --evals 11 20 --name bench_order4_substeps_1pct_amd

Writes OUT/NAME.json (default benchmarks/results/bench_order4_substeps.json) after every row
(rows it holds are skipped on a rerun).
"""

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np
from bench_step_convergence import TIGHT, _value_and_grad, against, policy_config
from machine import describe
from run_folder import add_run_arguments, run_designs

HERE = Path(__file__).resolve().parent


def configurations(scene, factors, substeps, dtype=None):
    """(label, configuration) of each row: Verlet at h with 4 contact substeps (the policy's
    configuration with contact before the fourth order), then the fourth order at each factor
    and substep count; in `dtype` where given."""
    from design_engine.solve.policy import with_contact

    base = with_contact(policy_config(scene, dtype))

    def solver(**kw):
        return dataclasses.replace(base, solver=dataclasses.replace(base.solver, **kw))

    out = [("Verlet at h, 4 substeps", solver(order=2, contact_substeps=4))]
    for factor in factors:
        for n in substeps:
            out.append((f"order 4 at {factor:g} h, {n} substeps", solver(
                order=4, contact_substeps=n, max_dt=base.solver.max_dt * factor)))
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_run_arguments(p, "strain_1pct")
    p.add_argument("--factors", nargs="+", type=float, default=[1.0, 1.5])
    p.add_argument("--substeps", nargs="+", type=int, default=[1, 2, 4])
    p.add_argument("--dtype", choices=["float32", "float64"],
                   help="every fixed step in this precision (default the policy's at the design)")
    p.add_argument("--name", default="bench_order4_substeps")
    p.add_argument("--out", type=Path, default=HERE / "results")
    args = p.parse_args(argv)
    if min(args.factors) <= 0 or min(args.substeps) < 1:
        p.error("--factors must be positive and --substeps at least 1")
    import diffrax

    from design_engine.solve.policy import contact_step_ratio
    from design_engine.solve.simulate import SimulationError, SolverConfig

    task, xs = run_designs(p, args.task, args.run, args.scene, args.evals)
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / f"{args.name}.json"
    doc = json.loads(path.read_text()) if path.exists() else {"designs": {}}
    doc.update(task=args.task, scene=args.scene, run=str(args.run), machine=describe())

    def save():
        path.write_text(json.dumps(doc, indent=1) + "\n")

    for e in args.evals:
        scene = task.scenes[args.scene].with_design(task.embed(xs[e - 1]))
        design = doc["designs"].setdefault(f"eval {e}", {"rows": {}})
        if "reference_J" not in design:
            ref_j, ref_g, ref_s, _ = _value_and_grad(scene, SolverConfig(
                solver=diffrax.Dopri8(), rtol=TIGHT[0], atol=TIGHT[1]))
            design.update(reference_J=ref_j, reference_grad=ref_g.tolist(),
                          reference_value_and_grad_s=ref_s)
            save()
        ref_j, ref_g = design["reference_J"], np.asarray(design["reference_grad"])
        for label, config in configurations(scene, args.factors, args.substeps, args.dtype):
            if label in design["rows"]:
                continue
            row = {"dt_us": config.solver.max_dt * 1e3, "dtype": config.dtype,
                   "machine": describe()}
            try:
                j, g, wall, health = _value_and_grad(scene, config)
                row.update(against(j, g, ref_j, ref_g), value_and_grad_s=wall,
                           energy_error=health.get("energy_error"),
                           contact_step_ratio=contact_step_ratio(config.solver, health, scene))
            except SimulationError as exc:
                row["error"] = str(exc)
            design["rows"][label] = row
            save()
            print(f"eval {e} / {args.scene} / {label} ({row['dt_us']:.1f} us): J "
                  f"{row.get('J_rel_err', np.nan):.1e}, cosine {row.get('grad_cosine', np.nan):.7f}"
                  f" in {row.get('value_and_grad_s', np.nan):.2f} s", flush=True)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
