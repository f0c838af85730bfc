"""Does halving the fixed step converge J on the designs a run produced? The evidence behind the
policy's half-step check (`policy.STEP_ERROR_TOLERANCE`) on scenes that start in contact.

For each design (the task's start and evaluations `--evals` of a run folder) and scene, the
policy's own configuration (`policy.choose_config` at that design: Verlet with contact and its
substeps, at 0.6 x the stability limit) solves the scene's objective J forward at the step
h and at h/2, h/4, ... (`--halvings`), and adaptive Dopri8 with contact solves it at rtol 1e-8 /
atol 1e-4 (the policy's fallback) and at rtol 1e-10 / atol 1e-8 (the reference of the issue's
re-check). Per row: each J, its relative error against the tight Dopri8, the half-step
estimate the policy would compute at each step (4/3 |J(h) - J(h/2)| / |J(h)|), the fallback's
own error, the work-energy drift of each fixed step and the wall time of each solve (compiled
first). Whether the estimate bounds the true error, and whether halving approaches the
reference, is what the policy's refinement on the estimate relies on.

    .venv/bin/python benchmarks/bench_step_convergence.py --run runs/fvp20 --evals 5 9 \
        --scenes strain_8pct --out benchmarks/results

`--newmark-iterations K` solves the same steps by implicit Newmark (trapezoidal, with contact,
K chord iterations on the factored stiffness of the start: `solve.implicit_step`) instead of
the policy's Verlet: whether an implicit step buys accuracy per second where Verlet needs small
steps.

`--order 4` solves the same steps by the fourth-order composition of Verlet steps
(`FixedStepVerlet(order=4)`: five force evaluations a step, contact substeps kept; rows keyed
`/ order 4`, also with `--gradients`; its `step_error` keeps Verlet's factor 4/3, where a
fourth-order step's Richardson factor is 16/15): whether a higher order buys accuracy per
second where Verlet needs small steps.

`--contact-substeps N` steps the contact forces N times per step
(`FixedStepVerlet.contact_substeps`; 1: with the rest) instead of the policy's number (rows
keyed `/ substeps N`): whether the error at the step is the barrier's.

`--gradients` instead solves value and gradient by the policy's fixed step at h, h/2, ... and
compares both with Dopri8's at rtol 1e-10 (key `gradients`: `J_rel_err`, `grad_cosine`,
`grad_rel_err`, `value_and_grad_s`): what the half-step check on J says of the gradient. With
`--dtype` or `--order`, in that precision or order (rows keyed ` / float64`, ` / order 4`, as
the forward rows).

`--adaptive-rtols R ...` instead times value and gradient by Dopri8 with contact at those rtols
(atol 1e-4, the fallback's, or each of `--adaptive-atols A ...`) against rtol 1e-10 on the same
designs (key `adaptive`: relative error of J, gradient cosine, wall time, steps): what the
fallback's tolerance buys; `--adaptive-solver Dopri5` or `Tsit5` times that solver instead.

`--contact-band-deg D` solves the scene (fixed step and both Dopri8 references) with a study
variant of the contact law whose curvature is ramped in over D degrees below the cutoff
(`c2_contact_law`: twice continuously differentiable, where the spec's law is C1 with a
curvature jump of k_c at the cutoff; rows keyed `/ c2 D deg`): whether the jump limits the
fixed step's convergence, of J or, with `--gradients`, of the gradient.

Writes OUT/bench_step_convergence.json after every row (rows it holds are skipped on a rerun).
"""

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from machine import describe
from run_folder import run_designs

TIGHT = (1e-10, 1e-8)
FALLBACK = (1e-8, 1e-4)


def c2_contact_law(band_rad: float):
    """A study variant of the spec's contact law (`energy.contact_law`, 5.3), C2 at the cutoff:
    the spec's barrier (`energy.contact_energy`, with (alpha - theta_c)^2 in its numerator) times
    f(d) / d^2, d = theta_c - alpha, where f(d) = d^3 / (3 b) for d < b and d^2 - b d + b^2 / 3
    beyond (value, slope and curvature continuous at b), the rest of the law unchanged."""
    import jax.numpy as jnp

    from design_engine.physics.energy import contact_energy

    def barrier(alpha, mat):
        b = jnp.asarray(band_rad, alpha.dtype)
        d = mat.contact_cutoff - alpha
        far = jnp.where(d < b, b, d)  # no division by a small d in the branch not taken
        ramp = jnp.where(d < b, d / (3.0 * b), 1.0 - b / far + b**2 / (3.0 * far**2))
        return contact_energy(alpha, mat.k_contact, mat.contact_min, mat.contact_cutoff) * ramp

    def law(m, mat):
        return {"contact": barrier(m.voids[:, 0], mat) + barrier(m.voids[:, 1], mat)}

    return law


def _timed(scene, config, gradient: bool):
    """The scene's objective by `config` (`run.make_objective`), compiled before the timed call:
    (J, health scalars, gradient [n_design] with `gradient` else None, wall s)."""
    import jax
    import jax.numpy as jnp

    from design_engine.solve.run import checked, make_objective

    fn = make_objective(scene, config)[0 if gradient else 1]
    x = jnp.asarray(scene.design)
    jax.block_until_ready(fn(x))  # compile
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(x))  # the call returns before its work is done
    wall = time.perf_counter() - t0
    (j, aux), g = out if gradient else (out, None)
    checked((j, aux), config)
    health = {k: float(np.asarray(v)) for k, v in aux.items() if np.asarray(v).ndim == 0}
    return float(j), health, None if g is None else np.asarray(g, np.float64), wall


def _solve(scene, config):
    """(J, health scalars, wall s) of the scene's objective (`_timed`)."""
    j, health, _, wall = _timed(scene, config, gradient=False)
    return j, health, wall


def _value_and_grad(scene, config):
    """(J, gradient [n_design], wall s, health scalars) of the scene's objective (`_timed`)."""
    j, health, g, wall = _timed(scene, config, gradient=True)
    return j, g, wall, health


def against(j: float, g: np.ndarray, ref_j: float, ref_g: np.ndarray) -> dict:
    """J's relative error, the gradient's cosine and relative error against a reference's."""
    return {"J_rel_err": abs(j - ref_j) / abs(ref_j),
            "grad_cosine": float(g @ ref_g / (np.linalg.norm(g) * np.linalg.norm(ref_g))),
            "grad_rel_err": float(np.linalg.norm(g - ref_g) / np.linalg.norm(ref_g))}


def adaptive_row(scene, rtols: list[float], atols: list[float] = (FALLBACK[1],),
                 solver: str = "Dopri8") -> dict:
    """Value and gradient by the adaptive `solver` (a diffrax class name) with contact at each
    of `rtols` and `atols` (default the fallback's atol) against Dopri8 at rtol 1e-10 / atol
    1e-8: relative error of J, gradient cosine, wall time, steps."""
    import diffrax

    from design_engine.solve.simulate import SolverConfig

    ref_j, ref_g, ref_s, _ = _value_and_grad(scene, SolverConfig(
        solver=diffrax.Dopri8(), rtol=TIGHT[0], atol=TIGHT[1]))
    rows = []
    for rtol, atol in ((r, a) for r in rtols for a in atols):
        config = SolverConfig(solver=getattr(diffrax, solver)(), rtol=rtol, atol=atol)
        j, g, wall, health = _value_and_grad(scene, config)
        steps = health.get("num_steps")
        rows.append({"solver": solver, "rtol": rtol, "atol": atol, "steps": steps,
                     **against(j, g, ref_j, ref_g), "value_and_grad_s": wall})
    return {"reference_value_and_grad_s": ref_s, "rows": rows}


def policy_config(scene, dtype: str | None = None, order: int = 2,
                  contact_substeps: int | None = None):
    """The policy's own configuration at the design (`policy.choose_config`), in `dtype`, with
    the fixed step of `order` and `contact_substeps` (contact on) where given, at Verlet's
    step h (the policy's fourth order in static contact takes `policy.verlet_multiple` x h)."""
    from design_engine.solve.policy import choose_config, verlet_multiple

    config = choose_config(scene).config
    if verlet_multiple(config.solver) > 1.0:
        config = dataclasses.replace(config, solver=dataclasses.replace(
            config.solver, max_dt=config.solver.max_dt / verlet_multiple(config.solver),
            finer_check=False))
    if dtype is not None:
        config = dataclasses.replace(config, dtype=dtype)
    solver = {"order": order}  # the policy's own is 4 where the pulse starts in contact
    if contact_substeps is not None:
        solver["contact_substeps"] = contact_substeps
        config = dataclasses.replace(config, use_contact=True)
    return dataclasses.replace(config, solver=dataclasses.replace(config.solver, **solver))


def gradient_row(scene, halvings: int, order: int = 2, dtype: str | None = None,
                 contact_substeps: int | None = None) -> dict:
    """Value and gradient by the policy's own fixed-step configuration at the design (as
    `row_for`, in `dtype` and with `contact_substeps` where given) at h, h/2, ... against Dopri8 at rtol 1e-10 / atol 1e-8:
    relative error of J, gradient cosine and relative error, wall time (compiled first)."""
    import diffrax

    from design_engine.solve.policy import refined
    from design_engine.solve.simulate import SimulationError, SolverConfig

    ref_j, ref_g, ref_s, _ = _value_and_grad(scene, SolverConfig(
        solver=diffrax.Dopri8(), rtol=TIGHT[0], atol=TIGHT[1]))
    config = policy_config(scene, dtype, order, contact_substeps)
    steps = []
    for _ in range(halvings + 1):
        try:
            j, g, wall, _ = _value_and_grad(scene, config)
            steps.append({"dt_us": config.solver.max_dt * 1e3,
                          **against(j, g, ref_j, ref_g), "value_and_grad_s": wall})
        except SimulationError as exc:
            steps.append({"dt_us": config.solver.max_dt * 1e3, "error": str(exc)})
        config = refined(config)
    return {"reference_value_and_grad_s": ref_s, "steps": steps}


def row_for(scene, halvings: int, dtype: str | None = None,
            newmark_iterations: int | None = None, order: int = 2,
            contact_substeps: int | None = None) -> dict:
    import diffrax

    from design_engine.solve.implicit_step import ImplicitNewmark
    from design_engine.solve.policy import refined, relative_step_error
    from design_engine.solve.simulate import SimulationError, SolverConfig

    ref_j, _, ref_s = _solve(scene, SolverConfig(solver=diffrax.Dopri8(), rtol=TIGHT[0],
                                                 atol=TIGHT[1]))
    fb_j, _, fb_s = _solve(scene, SolverConfig(solver=diffrax.Dopri8(), rtol=FALLBACK[0],
                                               atol=FALLBACK[1]))
    config = policy_config(scene, dtype, order, contact_substeps)
    if newmark_iterations is not None:  # implicit Newmark at the policy's step, with contact
        config = dataclasses.replace(config, solver=ImplicitNewmark(
            max_dt=config.solver.max_dt, iterations=newmark_iterations), use_contact=True)
    steps = []
    first = config
    for _ in range(halvings + 1):
        try:
            j, health, wall = _solve(scene, config)
            steps.append({"dt_us": config.solver.max_dt * 1e3, "J": j,
                          "J_rel_err": abs(j - ref_j) / abs(ref_j),
                          "energy_error": health.get("energy_error"),
                          "void_margin": health.get("void_margin"), "wall_s": wall})
        except SimulationError as exc:
            steps.append({"dt_us": config.solver.max_dt * 1e3, "error": str(exc)})
        config = (refined(config) if newmark_iterations is None else dataclasses.replace(
            config, solver=dataclasses.replace(config.solver,
                                               max_dt=config.solver.max_dt / 2)))
    for a, b in zip(steps, steps[1:]):
        if "J" in a and "J" in b:
            a["step_error"] = relative_step_error(a["J"], b["J"])
    return {"reference_J": ref_j, "reference_s": ref_s, "fallback_J": fb_j,
            "fallback_rel_err": abs(fb_j - ref_j) / abs(ref_j), "fallback_s": fb_s,
            "config": repr(first), "steps": steps}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--task", default="focus-vs-protect")
    p.add_argument("--scenes", nargs="*", help="scenes of the task (default: all)")
    p.add_argument("--run", type=Path, help="a `metarig design` run folder of the task")
    p.add_argument("--evals", nargs="*", type=int, default=[])
    p.add_argument("--no-start", action="store_true", help="skip the task's start design")
    p.add_argument("--halvings", type=int, default=3)
    p.add_argument("--dtype", choices=("float32", "float64"), help="the fixed step in this "
                   "precision instead of the policy's (rows keyed with it)")
    p.add_argument("--newmark-iterations", type=int, help="the fixed step by implicit Newmark "
                   "(trapezoidal, contact on) with this many chord iterations instead of the "
                   "policy's Verlet, at the same steps (rows keyed `/ newmark K`)")
    p.add_argument("--order", type=int, choices=(2, 4), default=2, help="4: the fixed step by "
                   "the fourth-order composition of Verlet steps (rows keyed `/ order 4`)")
    p.add_argument("--contact-substeps", type=int, help="the contact forces stepped this many "
                   "times per step instead of the policy's number (rows keyed `/ substeps N`)")
    p.add_argument("--gradients", action="store_true", help="instead of the forward step "
                   "sweep: value and gradient by the policy's fixed step at h, h/2, ... against "
                   "Dopri8 rtol 1e-10 (key `gradients`)")
    p.add_argument("--adaptive-rtols", nargs="*", type=float, default=[],
                   help="instead of the step sweep: value and gradient by Dopri8 at these "
                   "rtols against rtol 1e-10 (key `adaptive`)")
    p.add_argument("--adaptive-atols", nargs="*", type=float, default=[FALLBACK[1]],
                   help="with --adaptive-rtols: each of these atols too (default the "
                   "fallback's, 1e-4; rows keyed `/ atols ...` otherwise)")
    p.add_argument("--adaptive-solver", default="Dopri8", choices=("Dopri8", "Dopri5", "Tsit5"),
                   help="with --adaptive-rtols: the adaptive solver timed (rows keyed with it "
                   "unless Dopri8)")
    p.add_argument("--contact-band-deg", type=float, help="solve with a C2 variant of the "
                   "contact law, its curvature ramped in over this many degrees below the cutoff")
    p.add_argument("--out", type=Path, default=Path("runs/bench-step-convergence"))
    args = p.parse_args(argv)
    if args.contact_band_deg is not None and not args.contact_band_deg > 0:
        p.error(f"--contact-band-deg must be positive, got {args.contact_band_deg}")
    from design_engine.design.task import load_task
    from design_engine.physics.energy import Model

    task, xs = (run_designs(p, args.task, args.run) if args.run is not None
                else (load_task(args.task), []))
    designs = [] if args.no_start else [("start", np.asarray(task.initial_design))]
    designs += [(f"eval {e}", task.embed(xs[e - 1])) for e in args.evals if 1 <= e <= len(xs)]
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "bench_step_convergence.json"
    doc = json.loads(path.read_text()) if path.exists() else {"rows": {}}
    # each row says its machine (`machine` here: the last run's)
    doc.update(task=args.task, run=str(args.run) if args.run else None, machine=describe())
    # the mode: (key of the results part, row of one scene, its printed line)
    if args.gradients:
        part, make = "gradients", lambda sc: gradient_row(sc, args.halvings, args.order,
                                                          args.dtype, args.contact_substeps)

        def line(row):
            return ", ".join(f"{r['dt_us']:.1f} us J {r.get('J_rel_err', float('nan')):.1e} "
                             f"cosine {r.get('grad_cosine', float('nan')):.7f}"
                             for r in row["steps"])
    elif args.adaptive_rtols:
        part = "adaptive"

        def make(sc):
            return adaptive_row(sc, args.adaptive_rtols, args.adaptive_atols,
                                args.adaptive_solver)

        def line(row):
            return f"reference {row['reference_value_and_grad_s']:.1f} s; " + ", ".join(
                f"{r.get('solver', 'Dopri8')} rtol {r['rtol']:g} atol {r['atol']:g}, "
                f"{r.get('steps', float('nan')):.0f} steps: {r['J_rel_err']:.1e}, cosine {r['grad_cosine']:.7f}, "
                f"{r['value_and_grad_s']:.1f} s" for r in row["rows"])
    else:
        part = "rows"

        def make(sc):
            return row_for(sc, args.halvings, args.dtype, args.newmark_iterations, args.order,
                           args.contact_substeps)

        def line(row):
            return f"fallback {row['fallback_rel_err']:.1e}; " + ", ".join(
                f"{s['dt_us']:.1f} us {s.get('J_rel_err', float('nan')):.1e}"
                f" (est {s.get('step_error', float('nan')):.1e})" for s in row["steps"])
    # a row's key: the design, the scene and the options its mode takes
    options = (args.dtype, part == "rows" and args.newmark_iterations
               and f"newmark {args.newmark_iterations}",
               part != "adaptive" and args.order != 2 and f"order {args.order}",
               part != "adaptive" and args.contact_substeps is not None
               and f"substeps {args.contact_substeps}")
    suffix = "".join(f" / {v}" for v in options if v) if part != "adaptive" else ""
    model = (None if args.contact_band_deg is None
             else Model(contact=c2_contact_law(np.radians(args.contact_band_deg))))
    if part == "adaptive" and args.adaptive_atols != [FALLBACK[1]]:
        suffix = " / atols " + " ".join(f"{a:g}" for a in args.adaptive_atols)
    if part == "adaptive" and args.adaptive_solver != "Dopri8":
        suffix += f" / {args.adaptive_solver}"
    if args.contact_band_deg is not None:
        suffix += f" / c2 {args.contact_band_deg:g} deg"
    for label, x in designs:
        for name in args.scenes or list(task.scenes):
            key = f"{label} / {name}" + suffix
            if key in doc.setdefault(part, {}):
                continue
            scene = task.scenes[name].with_design(x)
            if model is not None:
                scene = dataclasses.replace(scene, model=model)
            row = make(scene) | {"machine": describe()}
            doc[part][key] = row
            path.write_text(json.dumps(doc, indent=1))
            print(f"{key}: {line(row)}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
