"""What a design run leaves in its folder: the design files (`design.json`, `last_design.json`)
with their provenance, a summary in the log, and the plots (`history.png`, `designs.png`,
`active_constraints.png`). Used by `metarig design`, the Pareto sweeps and the benchmarks."""

import datetime
import json
import logging
import subprocess
from pathlib import Path

import numpy as np

log = logging.getLogger("metarig.design")


def provenance(solver: dict | None = None) -> dict:
    """Package version, git commit (if any), date and solver configuration of a result."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        ver = version("metarig")
    except PackageNotFoundError:
        ver = "unknown"
    try:
        commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=Path(__file__).parent,
                                capture_output=True, text=True, timeout=5).stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        commit = None
    return {"package": "metarig", "version": ver, "git_commit": commit,
            "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
            "solver": solver}


def write_outputs(task, out: Path, result, plots: bool = True) -> None:
    """Design files, a summary in the log, and the plots of a finished (or stopped) run."""
    from design_engine.design.design_io import save_design

    evals = result.evaluations
    if not evals:
        log.info("no evaluation was completed; nothing to write")
        return
    last = len(evals) - 1
    _save(out / "last_design.json", task, result.last_x, evals[last], save_design)
    if result.best is None:
        log.warning("no feasible design among %d evaluations: design.json not written", len(evals))
    else:
        _save(out / "design.json", task, result.best_x, evals[result.best], save_design)
    first = evals[0]
    totals = {k: sum(e[k] for e in evals) for k in ("sim_s", "jac_s", "opt_s")}
    log.info("%s after %d evaluations (%s): compilations this session: %d",
             "interrupted" if result.status == "interrupted" else "stopped", len(evals),
             result.stop_reason, result.compilations)
    if result.best is not None:
        b = evals[result.best]
        ratio = b["objective"] / first["objective"] if first["objective"] else float("nan")
        log.info("objective %.6g -> %.6g (best feasible, evaluation %d; x%.1f)",
                 first["objective"], b["objective"], b["eval"], ratio)
    log.info("time: simulation %.1f s, constraint Jacobians %.1f s, optimiser step %.1f s",
             totals["sim_s"], totals["jac_s"], totals["opt_s"])
    if result.status == "interrupted":
        mat = task.document.get("material")
        log.info("resume with: metarig design %s --out %s --resume%s", task.source, out,
                 f" --material {mat['file']}" if mat else "")
    if plots:
        try:
            _plots(task, out, result)
        except Exception as exc:  # a plot must never cost the run's results
            log.warning("plots failed: %s", exc)
    log.info("wrote %s", ", ".join(sorted(f.name for f in out.iterdir())))


def _save(path: Path, task, x, rec: dict, save_design) -> None:
    from design_engine.physics.geometry import InvalidDesignError

    try:
        _write_design(path, task, x, rec, save_design)
    except InvalidDesignError as exc:
        log.warning("%s not written: evaluation %d is no valid design (%s)", path.name,
                    rec["eval"], exc)


def _write_design(path: Path, task, x, rec: dict, save_design) -> None:
    save_design(path, task.lattice, x, name=f"{task.name} (evaluation {rec['eval']})",
                task=task.name, task_source=task.source, goal=task.goal,
                objective=rec["objective"], objectives=rec["objectives"],
                objectives_units={t.name: ("kg m^2/s" if t.quantity == "angular_momentum"
                                           else "J (mean kinetic energy over the window)")
                                  for t in task.terms},
                max_constraint=rec["max_constraint"], feasible=rec["feasible"],
                eval=rec["eval"], provenance=provenance(rec.get("solver")))


def _plots(task, out: Path, result) -> None:
    import jax.numpy as jnp

    from design_engine.design.constraints import active_constraint_masks, make_sparse_constraints
    from design_engine.design.plots import (plot_active_constraints, plot_design_comparison,
                                            plot_history)
    from design_engine.physics.geometry import block_geometry
    from design_engine.solve.objectives import block_kinetic_energy
    from design_engine.solve.run import simulate_scene

    plot_history(out / "history.png", result.evaluations, task.goal,
                 f"{task.name}: objective per evaluation")
    final = result.best_x if result.best_x is not None else result.last_x
    scene = task.scenes[task.terms[0].scene]
    maps = []
    for x in (task.initial_design, final):
        sc = scene.with_design(x)
        run = simulate_scene(sc)
        maps.append((sc.reference_polygons_m(),
                     np.asarray(block_kinetic_energy(run.solution)).mean(axis=0) * 1e-3))
    plot_design_comparison(out / "designs.png", maps[0][0], maps[0][1], maps[1][0], maps[1][1],
                           task.targets, f"{task.name}: initial and optimised design "
                           f"({scene.name} scene)")
    g, _ = make_sparse_constraints(task.lattice, task.limits, final, task.free)(final[task.free])
    masks = active_constraint_masks(task.lattice, g)
    geom = block_geometry(task.lattice, jnp.asarray(final))
    nodes = np.asarray(geom.centroids[:, None, :] + geom.arms).reshape(-1, 2) / 1e3
    bond_points = nodes[task.lattice.bonds].mean(axis=1)
    plot_active_constraints(out / "active_constraints.png", maps[1][0], masks["edges"],
                            masks["vertices"], masks["voids"], bond_points,
                            f"{task.name}: active constraints of the final design")
    (out / "active_constraints.json").write_text(json.dumps(masks["counts"]))
