"""Static pre-compression on the 24x18 protection scene: the figures of the README's "Static
pre-compression" section. Writes benchmarks/results/bench_statics.json; each part replaces its
own key there and keeps the others.

    .venv/bin/python benchmarks/bench_statics.py [--parts timing,hessian,branches,ramp,cholesky]
                                                 [--strains 0.01,0.05,0.08]
    .venv/bin/python benchmarks/bench_statics.py --parts leveltol [--seeds 2]
    .venv/bin/python benchmarks/bench_statics.py --parts warm --run RUN_DIR
    .venv/bin/python benchmarks/bench_statics.py --parts bound --run RUN_DIR [--bounds 0.25,0.5]

Parts:
- `timing` (key `strains`): wall time of the equilibrium and of a value and gradient through it
  (a functional of the equilibrium), first call (compile included) and warm, at `--strains`;
  the load levels the continuation took and the equilibrium's energy.
- `hessian`: at the 8 % equilibrium, the exact sparse Hessian (`statics.make_sparse_hessian`,
  one Hessian-vector product per colour and DOF) against the dense `jax.hessian`: the number of
  products, both warm times, their ratio and the largest difference.
- `branches`: which equilibrium the continuation reaches at 8 %: N equal load levels without
  the 0.1 mm bound (N = 8, 32, 48, 64, 100) against the default bound; and the dynamic ramp's
  end state (Dopri8 at the reference tolerances with contact, no pulse) relaxed by Newton at
  5 % and 8 %, against the static solve of the same closing.
- `ramp`: the static start against the reference's dynamic ramp, mean target kinetic energy
  J/N_t and mean total kinetic energy over the window at 0, 1, 2, 5 and 8 %, both solved with
  Dopri8 at the reference tolerances with contact (contact -10/-5 deg, target (2,2)@(2,2)),
  beside the reference's own values; and the Dopri5 steps of the baseline (spec tolerances,
  ramp) at 8 %.
- `cholesky` (key `cholesky`): the equilibrium and a value and gradient through it with the
  Newton steps solved by the block Cholesky in the Hessian's banded order (the default,
  `linalg.make_sparse_spd_solve`) against the dense Cholesky, side by side at `--strains`:
  warm wall and CPU times (best of 3), load levels, and the largest differences of the
  equilibrium and of the gradient.
- `leveltol` (key `level_tol`; not in the default parts): the continuation's intermediate load
  levels stopped at `statics.LEVEL_TOL` (the default) against all solved to `GRADIENT_TOL`,
  side by side at `--strains` on the task's periodic start and `--seeds` seeded random starts:
  warm wall and CPU times (best of 3), levels, and the largest difference of the equilibria.
- `warm` (not in the default parts; `--run` a `metarig design focus-vs-protect` run folder):
  the equilibrium of each evaluation's design followed from the previous evaluation's
  (`make_static_solver(..., guess=...)`, a continuation in the design) against the load
  continuation from rest, at each of the task's strains: wall times (compiled), levels, and
  whether both reached the same equilibrium (largest difference of the free DOFs).
- `bound` (not in the default parts; `--run` as for `warm`): the load continuation from rest with
  its step bound (`statics.MAX_LOAD_STEP_MM`, 0.1 mm) against each of `--bounds` (1e9: none, so
  `statics.N_LOAD` levels at least), on each evaluation's design at each of the task's strains:
  wall times (compiled), levels, and whether each reached the default's equilibrium (largest
  difference of the free DOFs, same below 1e-6). `--level-tols` adds, the same way, the default
  bound with the intermediate levels stopped at each of those residuals (then under key
  `bound_level_tol`, per run folder, so that the bounds' record stays).
"""

import argparse
import dataclasses
import json
import os
import platform
import time
from pathlib import Path

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

from design_engine import build_scene
from design_engine.physics import statics
from design_engine.physics.energy import bond_geometry, make_energy
from design_engine.physics.geometry import block_geometry
from design_engine.physics.loading import make_prescribed
from design_engine.physics.statics import make_sparse_hessian, make_static_solver
from design_engine.solve.policy import contact_config
from design_engine.solve.run import simulate_scene
from design_engine.solve.simulate import SolverConfig, make_simulator
from run_folder import run_designs

OUT = Path(__file__).resolve().parent / "results" / "bench_statics.json"
SCENE = "protection-24x18"
# The reference implementation's J/N_t (mJ) on this scene with its dynamic ramp, as issue 12
# quotes them (24x18, contact -10/-5 deg, target (2,2)@(2,2)); and its mean total kinetic energy
# over the window (mJ) of the two-stage runs, spec 11.11.
REFERENCE_J_MJ = {"0": 0.1083, "0.02": 0.1028, "0.05": 0.1476}
REFERENCE_TOTAL_KE_MJ = {"0.01": 6.678, "0.08": 7.540}


def timed(fn, *args):
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    return out, time.perf_counter() - t0


def timed_cpu(fn, *args):
    """(out, wall s, CPU s of this process: all its threads, less sensitive to other load)."""
    t0, c0 = time.perf_counter(), time.process_time()
    out = jax.block_until_ready(fn(*args))
    return out, time.perf_counter() - t0, time.process_time() - c0


def _timing(strain: float) -> dict:
    s = build_scene(SCENE, strain=strain)
    ld, x = s.loading, jnp.asarray(s.design)
    eq = make_static_solver(s.lattice, s.supports)
    w = jnp.asarray(np.random.default_rng(0).normal(size=s.supports.free.size))
    solve = jax.jit(lambda x: eq(x, s.material, ld, ld.precompression_time))
    vg = jax.jit(jax.value_and_grad(
        lambda x: jnp.dot(eq(x, s.material, ld, ld.precompression_time)[0], w)))
    (_, info), first = timed(solve, x)
    _, warm, warm_cpu = min((timed_cpu(solve, x) for _ in range(3)), key=lambda r: r[1])
    _, vg_first = timed(vg, x)
    _, vg_warm, vg_cpu = min((timed_cpu(vg, x) for _ in range(3)), key=lambda r: r[1])
    return {"n_free": int(s.supports.free.size), "solve_first_s": first, "solve_s": warm,
            "solve_cpu_s": warm_cpu, "value_and_grad_first_s": vg_first,
            "value_and_grad_s": vg_warm, "value_and_grad_cpu_s": vg_cpu,
            "note": "warm: best of 3 by wall time",
            "levels": int(info["levels"]), "gradient_norm": float(info["gradient_norm"]),
            "energy_mJ": float(info["energy"])}


def parts_timing(strains) -> dict:
    rows = {}
    for strain in strains:
        rows[f"{strain:g}"] = _timing(strain)
        print(strain, rows[f"{strain:g}"], flush=True)
    return rows


def _energy_of_free(scene, t_hold):
    """total(q_f) of the scene's energy with contact, prescribed DOFs at their values at t_hold."""
    energy = make_energy(scene.lattice, use_contact=True)
    bonds = bond_geometry(scene.lattice, block_geometry(scene.lattice, jnp.asarray(scene.design)))
    qc = make_prescribed(scene.supports)[0](jnp.asarray(t_hold), scene.loading)
    index = np.asarray(scene.supports.assemble_index)

    def total(qf):
        return energy(jnp.concatenate([qf, qc])[index].reshape(-1, 3), bonds, scene.material)

    return total


def part_hessian(strain: float = 0.08) -> dict:
    s = build_scene(SCENE, strain=strain)
    ld = s.loading
    qf, _ = jax.jit(make_static_solver(s.lattice, s.supports))(
        jnp.asarray(s.design), s.material, ld, ld.precompression_time)
    total = _energy_of_free(s, ld.precompression_time)
    grad = jax.grad(total)
    sparse_fn = make_sparse_hessian(s.lattice, np.asarray(s.supports.free), lambda q: grad(q))
    sparse = jax.jit(sparse_fn)
    dense = jax.jit(jax.hessian(total))
    hs, sparse_first = timed(sparse, qf)
    hd, dense_first = timed(dense, qf)
    sparse_s = min(timed(sparse, qf)[1] for _ in range(3))
    dense_s = min(timed(dense, qf)[1] for _ in range(3))
    diff = float(jnp.max(jnp.abs(hs - hd)) / jnp.max(jnp.abs(hd)))
    row = {"strain": strain, "n_free": int(qf.size), "hessian_vector_products": sparse_fn.n_seeds,
           "sparse_s": sparse_s, "dense_s": dense_s, "dense_over_sparse": dense_s / sparse_s,
           "sparse_first_s": sparse_first, "dense_first_s": dense_first,
           "max_rel_difference": diff, "note": "warm times, best of 3"}
    print("hessian", row, flush=True)
    return row


def _relax(total, q0, iters: int = 60):
    """Damped Newton on total(q_f) from q0 with the dense Hessian, until max |g| <= 1e-10:
    (q, energy, max |g|, iterations)."""
    grad, hess = jax.jit(jax.grad(total)), jax.jit(jax.hessian(total))
    f = jax.jit(total)
    q, mu, done = jnp.asarray(q0), 1e-8, 0
    for _ in range(iters):
        g = grad(q)
        if float(jnp.max(jnp.abs(g))) <= statics.GRADIENT_TOL:
            break
        done += 1
        h = hess(q)
        scale = float(jnp.max(jnp.abs(jnp.diag(h))))
        e0 = float(f(q))
        for _ in range(12):
            d = jnp.linalg.solve(h + mu * scale * jnp.eye(q.size), -g)
            e1 = float(f(q + d))
            if np.isfinite(e1) and e1 <= e0 + 1e-13 * abs(e0):
                q, mu = q + d, max(mu / 3, 1e-12)
                break
            mu *= 10
    return q, float(f(q)), float(jnp.max(jnp.abs(grad(q)))), done


def part_branches() -> dict:
    out = {"equal_levels_8pct": {}, "ramp_end_relaxed": {}}
    s = build_scene(SCENE, strain=0.08)
    ld, x = s.loading, jnp.asarray(s.design)
    for n in (8, 32, 48, 64, 100):  # no displacement bound: N equal levels
        eq = jax.jit(make_static_solver(s.lattice, s.supports, n_load=n, max_load_step_mm=1e9))
        _, info = eq(x, s.material, ld, ld.precompression_time)
        out["equal_levels_8pct"][str(n)] = {"energy_mJ": float(info["energy"]),
                                            "levels": int(info["levels"]),
                                            "gradient_norm": float(info["gradient_norm"])}
        print("levels", n, out["equal_levels_8pct"][str(n)], flush=True)
    for strain in (0.05, 0.08):
        r = build_scene(SCENE, strain=strain, precompression="ramp")
        lr = dataclasses.replace(r.loading, amplitude=0.0)
        tc = lr.precompression_time
        q_static, info = jax.jit(make_static_solver(r.lattice, r.supports))(
            jnp.asarray(r.design), r.material, lr, tc)
        sim = make_simulator(r.lattice, r.supports, contact_config())
        t0 = time.perf_counter()
        sol = sim(jnp.asarray(r.design), r.material, lr, jnp.asarray([0.5 * tc, tc]))
        ramp_s = time.perf_counter() - t0
        free = np.asarray(r.supports.free)
        q_end = np.asarray(sol.q).reshape(2, -1)[1, free]
        total = _energy_of_free(r, tc)
        q_rel, e_rel, g_rel, iters = _relax(total, q_end)
        out["ramp_end_relaxed"][f"{strain:g}"] = {
            "ramp_ms": float(tc), "ramp_end_energy_mJ": float(jax.jit(total)(jnp.asarray(q_end))),
            "relaxed_energy_mJ": e_rel, "relaxed_gradient_norm": g_rel, "newton_iterations": iters,
            "static_energy_mJ": float(info["energy"]), "static_levels": int(info["levels"]),
            "max_abs_diff_relaxed_vs_static": float(np.abs(np.asarray(q_rel)
                                                           - np.asarray(q_static)).max()),
            "ramp_solve_s": ramp_s}
        print("ramp end", strain, out["ramp_end_relaxed"][f"{strain:g}"], flush=True)
    out["levels_default"] = {}
    for strain in (0.01, 0.05, 0.08):
        s = build_scene(SCENE, strain=strain)
        _, info = jax.jit(make_static_solver(s.lattice, s.supports))(
            jnp.asarray(s.design), s.material, s.loading, s.loading.precompression_time)
        out["levels_default"][f"{strain:g}"] = {"levels": int(info["levels"]),
                                               "energy_mJ": float(info["energy"])}
    print("default levels", out["levels_default"], flush=True)
    return out


def _window(scene, config) -> dict:
    run = simulate_scene(scene, config)
    m = run.metrics
    return {"J_mean_mJ": m["target_ke_mean_J"] * 1e3, "total_ke_mean_mJ": m["total_ke_mean_J"] * 1e3,
            "total_ke_max_mJ": m["total_ke_max_J"] * 1e3, "steps": m["solver"]["num_steps"],
            "wall_s": run.wall_s}


def part_ramp(strains=(0.0, 0.01, 0.02, 0.05, 0.08)) -> dict:
    rows = {}
    for strain in strains:
        key = f"{strain:g}"
        static = _window(build_scene(SCENE, strain=strain), contact_config())
        row = {"static": static}
        if strain > 0:
            ramp = _window(build_scene(SCENE, strain=strain, precompression="ramp"),
                           contact_config())
            row["ramp"] = ramp
            row["static_vs_ramp"] = static["J_mean_mJ"] / ramp["J_mean_mJ"] - 1
            row["total_ke_ramp_vs_static"] = (ramp["total_ke_mean_mJ"]
                                              / static["total_ke_mean_mJ"] - 1)
        if key in REFERENCE_J_MJ:
            row["reference_J_mean_mJ"] = REFERENCE_J_MJ[key]
        if key in REFERENCE_TOTAL_KE_MJ:
            row["reference_total_ke_mean_mJ"] = REFERENCE_TOTAL_KE_MJ[key]
        rows[key] = row
        print("ramp", key, row, flush=True)
    base = _window(build_scene(SCENE, strain=0.08, precompression="ramp"),
                   SolverConfig(solver=diffrax.Dopri5()))
    print("baseline steps at 8 %", base, flush=True)
    return {"config": "Dopri8, rtol 1e-8, atol 1e-4, with contact, float64",
            "rows": rows, "baseline_dopri5_ramp_8pct": base}


def part_warm(run: Path, task, xs: np.ndarray) -> dict:
    """See the module docstring (`warm`): run folder `run`'s designs `xs` of `task`."""
    out = {"run": str(run), "evaluations": len(xs), "scenes": {}}
    for name, sc in task.scenes.items():
        solver = make_static_solver(sc.lattice, sc.supports, model=sc.model)
        cold = jax.jit(solver)
        warm = jax.jit(lambda x, m, ld, t, g, f=solver: f(x, m, ld, t, g))
        rows, prev = [], None
        for k in range(len(xs)):
            x = jnp.asarray(task.embed(xs[k]))
            if k == 0:
                cold(x, sc.material, sc.loading, 0.0)  # compiled before timing
            (q, info), tc = timed(cold, x, sc.material, sc.loading, 0.0)
            if prev is not None:
                if k == 1:
                    warm(x, sc.material, sc.loading, 0.0, prev)  # compiled before timing
                (qw, iw), tw = timed(warm, x, sc.material, sc.loading, 0.0, prev)
                diff = float(jnp.max(jnp.abs(q - qw)))
                rows.append({"eval": k + 1, "design_change_mm": float(jnp.max(jnp.abs(
                    x - prev[0]))), "cold_s": tc, "cold_levels": int(info["levels"]),
                    "warm_s": tw, "warm_levels": int(iw["levels"]),
                    "followed": int(iw["levels"]) <= 0, "max_difference": diff,
                    "same_equilibrium": diff < 1e-6})
                print(f"{name} evaluation {k + 1}: {rows[-1]}", flush=True)
            prev = (x, q)
        out["scenes"][name] = rows
    return out


def part_bound(run: Path, task, xs: np.ndarray, bounds: list[float],
               level_tols: list[float] = ()) -> dict:
    """See the module docstring (`bound`): run folder `run`'s designs `xs` of `task`."""
    out = {"run": str(run), "evaluations": len(xs), "bounds_mm": bounds,
           "level_tols": list(level_tols), "default_level_tol": statics.LEVEL_TOL, "scenes": {}}
    for name, sc in task.scenes.items():
        settings = ({f"{b:g} mm": {"max_load_step_mm": b}
                     for b in [statics.MAX_LOAD_STEP_MM, *bounds]}
                    | {f"level_tol {t:g}": {"level_tol": t} for t in level_tols})
        solvers = {key: jax.jit(make_static_solver(sc.lattice, sc.supports, model=sc.model, **kw))
                   for key, kw in settings.items()}
        rows = []
        for k in range(len(xs)):
            x = jnp.asarray(task.embed(xs[k]))
            row, ref = {"eval": k + 1}, None
            for b, solver in solvers.items():
                if k == 0:
                    solver(x, sc.material, sc.loading, 0.0)  # compiled before timing
                (q, info), wall = timed(solver, x, sc.material, sc.loading, 0.0)
                entry = {"wall_s": wall, "levels": int(info["levels"]),
                         "gradient_norm": float(info["gradient_norm"])}
                if ref is None:
                    ref = q
                else:
                    entry["max_difference"] = float(jnp.max(jnp.abs(q - ref)))
                    entry["same_equilibrium"] = entry["max_difference"] < 1e-6
                row[b] = entry
            rows.append(row)
            print(f"{name} evaluation {k + 1}: " + ", ".join(
                f"{key} {e['levels']} levels {e['wall_s']:.2f} s"
                + (f" diff {e['max_difference']:.1e}" if "max_difference" in e else "")
                for key, e in row.items() if key != "eval"), flush=True)
        out["scenes"][name] = rows
    return out


def part_cholesky(strains: list[float]) -> dict:
    """Banded block Cholesky (the default) against the dense one, side by side per strain."""
    from design_engine.physics import linalg

    def dense(n, rows, cols, **kw):
        return linalg.make_sparse_spd_solve(n, rows, cols, min_blocks=10**9, **kw)

    out = {}
    for strain in strains:
        s = build_scene(SCENE, strain=strain)
        x, t = jnp.asarray(s.design), s.loading.precompression_time
        w = jnp.asarray(np.random.default_rng(0).normal(size=s.supports.free.size))
        row, results = {}, {}
        for name, factory in (("banded", linalg.make_sparse_spd_solve), ("dense", dense)):
            statics.make_sparse_spd_solve = factory
            try:
                eq = jax.jit(make_static_solver(s.lattice, s.supports))
            finally:
                statics.make_sparse_spd_solve = linalg.make_sparse_spd_solve
            vg = jax.jit(jax.value_and_grad(
                lambda x, eq=eq, s=s, t=t, w=w: jnp.dot(eq(x, s.material, s.loading, t)[0], w)))
            (q, info), _ = timed(eq, x, s.material, s.loading, t)  # compiles
            (_, g), _ = timed(vg, x)
            eq_t = min(timed_cpu(eq, x, s.material, s.loading, t)[1:] for _ in range(3))
            vg_t = min(timed_cpu(vg, x)[1:] for _ in range(3))
            results[name] = (np.asarray(q), np.asarray(g))
            row[name] = {"equilibrium_s": eq_t[0], "equilibrium_cpu_s": eq_t[1],
                         "value_and_grad_s": vg_t[0], "value_and_grad_cpu_s": vg_t[1],
                         "levels": int(info["levels"])}
            print(f"{strain:.2f} {name}: equilibrium {eq_t[0]:.2f} s, value and gradient "
                  f"{vg_t[0]:.2f} s, {int(info['levels'])} levels", flush=True)
        solve = linalg.make_sparse_spd_solve(s.supports.free.size, *make_sparse_hessian(
            s.lattice, np.asarray(s.supports.free), lambda q: q).pattern)
        (qb, gb), (qd, gd) = results["banded"], results["dense"]
        row.update(blocks=solve.blocks, block_size=solve.block_size,
                   n_free=int(s.supports.free.size),
                   speedup_equilibrium=row["dense"]["equilibrium_s"]
                   / row["banded"]["equilibrium_s"],
                   max_state_difference=float(np.max(np.abs(qb - qd))),
                   max_gradient_difference_rel=float(np.max(np.abs(gb - gd))
                                                     / np.max(np.abs(gd))))
        out[f"{strain:g}"] = row
    return out


def part_level_tol(strains: list[float], seeds: int) -> dict:
    """Intermediate load levels stopped at `statics.LEVEL_TOL` (the default) against every level
    solved to `GRADIENT_TOL`, side by side per strain, on the task's periodic start and `seeds`
    seeded random starts (`load_task(..., seed=k)`): warm wall times (best of 3), load levels,
    and the largest differences of the equilibrium (whether both reached the same one)."""
    from design_engine.design.task import load_task

    designs = {"periodic": None} | {f"seed {k}": k for k in range(1, seeds + 1)}
    out = {}
    for strain in strains:
        s = build_scene(SCENE, strain=strain)
        t = s.loading.precompression_time
        solvers = {}
        for name, tol in (("level_tol", statics.LEVEL_TOL), ("every_level", statics.GRADIENT_TOL)):
            solvers[name] = jax.jit(make_static_solver(s.lattice, s.supports, level_tol=tol))
            timed(solvers[name], jnp.asarray(s.design), s.material, s.loading, t)  # compiles
        rows = {}
        for label, seed in designs.items():
            x = jnp.asarray(s.design if seed is None else load_task(
                "focus-vs-protect", seed=seed).initial_design)
            row, states = {}, {}
            for name, eq in solvers.items():
                (q, info), _ = timed(eq, x, s.material, s.loading, t)
                best = min(timed_cpu(eq, x, s.material, s.loading, t)[1:] for _ in range(3))
                states[name] = np.asarray(q)
                row[name] = {"equilibrium_s": best[0], "equilibrium_cpu_s": best[1],
                             "levels": int(info["levels"]),
                             "gradient_norm": float(info["gradient_norm"]),
                             "energy_mJ": float(info["energy"])}
            row["speedup"] = row["every_level"]["equilibrium_s"] / row["level_tol"]["equilibrium_s"]
            row["max_state_difference"] = float(np.max(np.abs(states["level_tol"]
                                                              - states["every_level"])))
            rows[label] = row
            print(f"{strain:.2f} {label}: {row['level_tol']['equilibrium_s']:.2f} s against "
                  f"{row['every_level']['equilibrium_s']:.2f} s, levels "
                  f"{row['level_tol']['levels']}/{row['every_level']['levels']}, state "
                  f"difference {row['max_state_difference']:.1e}", flush=True)
        out[f"{strain:g}"] = rows
    return {"level_tol": statics.LEVEL_TOL, "gradient_tol": statics.GRADIENT_TOL, "rows": out}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--parts", default="timing,hessian,branches,ramp,cholesky")
    p.add_argument("--strains", default="0.01,0.05,0.08", help="strains of the timing part")
    p.add_argument("--seeds", type=int, default=2, help="seeded random starts of the "
                   "leveltol part, beside the periodic one")
    p.add_argument("--run", type=Path, help="the warm and bound parts' `metarig design "
                   "focus-vs-protect` run folder")
    p.add_argument("--level-tols", default="", help="the bound part's intermediate level "
                   "residuals (N, N mm), each against the default, at the default bound")
    p.add_argument("--bounds", default="0.25,0.5,1e9", help="the bound part's load step bounds "
                   "(mm), each against the default")
    args = p.parse_args(argv)
    parts = args.parts.split(",")
    for part in sorted({"warm", "bound"} & set(parts)):
        if args.run is None:
            p.error(f"--parts {part} needs --run DIR, a focus-vs-protect run folder")
    if {"warm", "bound"} & set(parts):
        task, xs = run_designs(p, "focus-vs-protect", args.run)
    unknown = set(parts) - {"timing", "hessian", "branches", "ramp", "cholesky", "leveltol",
                            "warm", "bound"}
    if unknown:
        p.error(f"unknown parts: {', '.join(sorted(unknown))}")
    doc = json.loads(OUT.read_text()) if OUT.exists() else {}
    doc["scene"] = SCENE
    for part in parts:
        machine = {"cpus": os.cpu_count(), "platform": platform.platform(),
                   "XLA_FLAGS": os.environ.get("XLA_FLAGS", ""),
                   "load_before": os.getloadavg()}
        if part == "timing":
            doc["strains"] = parts_timing([float(v) for v in args.strains.split(",")])
            doc["machine"] = dict(machine, load_after=os.getloadavg())
        elif part == "hessian":
            doc["hessian"] = part_hessian()
        elif part == "branches":
            doc["branches"] = part_branches()
        elif part == "ramp":
            doc["ramp"] = part_ramp()
        elif part == "cholesky":
            doc["cholesky"] = part_cholesky([float(v) for v in args.strains.split(",")])
        elif part == "leveltol":
            doc["level_tol"] = part_level_tol([float(v) for v in args.strains.split(",")],
                                              args.seeds)
        elif part == "warm":
            doc["warm"] = part_warm(args.run, task, xs)
        elif part == "bound":
            tols = [float(v) for v in args.level_tols.split(",") if v]
            bounds = [float(v) for v in args.bounds.split(",") if v]
            found = part_bound(args.run, task, xs, bounds, tols)
            if tols:
                doc.setdefault("bound_level_tol", {})[str(args.run)] = found
            else:
                doc["bound"] = found
        machine["load_after"] = os.getloadavg()
        doc.setdefault("machine_per_part", {})[part] = dict(machine)
        OUT.write_text(json.dumps(doc, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
