"""Fixed-step Verlet *with* contact against adaptive Dopri8 on scenes in contact (value+gradient).

A measurement for the contact policy (not a policy change): on each scene, value-and-gradient
of the target energy by adaptive Dopri8 at rtol 1e-10 / atol 1e-6 (the reference), Dopri8 at
the reference tolerances (today's contact configuration), and velocity Verlet with contact in
float32 and float64 at the step the automatic policy takes for the design (0.6 x 2/omega_max),
reporting J and gradient errors against the reference, the gradient cosine, the wall time, and
how deep the deepest void went into the barrier (0 at the cutoff, 1 at the asymptote).

Scenes: the optimised 24x16 focusing design (`results/design_focusing-24x16.json`, in contact
under the pulse), any design files given with --designs (e.g. a run's intermediate designs),
and an 8x6 lattice with a 44 deg bias (2 deg voids) under a 6 mm pulse, where the barrier is
hit hard. JSON in --out/bench_contact_step.json.

`--profile` measures instead what one Verlet step costs on the first design, forward and
value-and-gradient, with and without contact, float64 and float32, against the pieces of a step
and the arithmetic of a force evaluation (`profile`); JSON in
--out/bench_contact_step_profile.json (or --name).

    .venv/bin/python benchmarks/bench_contact_step.py
    .venv/bin/python benchmarks/bench_contact_step.py --profile --out benchmarks/results
"""

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--designs", nargs="*", default=[str(HERE / "results" /
                                                        "design_focusing-24x16.json")])
    p.add_argument("--out", type=Path, default=Path("runs/bench-contact-step"))
    p.add_argument("--profile", action="store_true", help="per-step cost instead of accuracy")
    p.add_argument("--repeats", type=int, default=3, help="timed calls per measurement (best)")
    p.add_argument("--name", default="bench_contact_step_profile",
                   help="--profile: stem of the JSON file written under --out")
    args = p.parse_args(argv)

    import diffrax
    import jax
    import jax.numpy as jnp

    import design_engine  # noqa: F401
    from design_engine.design.design_io import load_design
    from design_engine.physics.scenes import build_scene
    from design_engine.solve.fixed_step import FixedStepVerlet
    from design_engine.solve.objectives import region_energy
    from design_engine.solve.policy import max_angular_frequency
    from design_engine.solve.simulate import SimulationError, SolverConfig, make_simulator

    scenes = {}
    for path in args.designs:
        lattice, x = load_design(path)
        scenes[Path(path).stem] = build_scene("focusing-24x16", nx=lattice.shape[0],
                                              ny=lattice.shape[1], design=x)
    scenes["8x6-bias44-6mm"] = build_scene("focusing-24x16", nx=8, ny=6, bias_angle_deg=44.0,
                                           amplitude_m=6e-3)
    args.out.mkdir(parents=True, exist_ok=True)
    report = {"machine": {"platform": platform.platform(), "cpus": os.cpu_count(),
                          "load_average_start": os.getloadavg()}, "scenes": {}}
    if args.profile:
        name, scene = next(iter(scenes.items()))
        dt = 0.6 * 2.0 / max_angular_frequency(scene)
        print(f"{name}: Verlet at dt = {dt * 1e3:.1f} us (0.6 x 2/omega_max)", flush=True)
        report["scenes"][name] = profile(scene, dt, args.repeats)
        report["machine"]["load_average_end"] = os.getloadavg()
        (args.out / f"{args.name}.json").write_text(json.dumps(report, indent=1))
        return 0

    def value_and_grad(scene, config):
        sim = make_simulator(scene.lattice, scene.supports, config, scene.sample_times)
        ids = np.asarray(next(iter(scene.targets.values())))

        def f(x):
            sol = sim(x, scene.material, scene.loading, jnp.asarray(scene.sample_times))
            return region_energy(sol, ids), sol.min_void_margin

        fn = jax.jit(jax.value_and_grad(f, has_aux=True))
        x = jnp.asarray(scene.design)
        jax.block_until_ready(fn(x))
        t0 = time.perf_counter()
        (v, margin), g = jax.block_until_ready(fn(x))
        return float(v), np.asarray(g, np.float64), float(margin), time.perf_counter() - t0

    for name, scene in scenes.items():
        dt = 0.6 * 2.0 / max_angular_frequency(scene)
        span = scene.material.contact_cutoff - scene.material.contact_min
        configs = {"dopri8 rtol 1e-10 (reference)": SolverConfig(solver=diffrax.Dopri8(),
                                                                  rtol=1e-10, atol=1e-6),
                   "dopri8 rtol 1e-8 (contact default)": SolverConfig(solver=diffrax.Dopri8()),
                   "verlet+contact float32": SolverConfig(solver=FixedStepVerlet(max_dt=dt),
                                                          dtype="float32"),
                   "verlet+contact float64": SolverConfig(solver=FixedStepVerlet(max_dt=dt))}
        rows, ref = {}, None
        for label, cfg in configs.items():
            try:
                v, g, margin, wall = value_and_grad(scene, cfg)
            except SimulationError as exc:
                rows[label] = {"failed": str(exc)}
                continue
            if ref is None:
                ref = (v, g)
            ok = np.isfinite(v) and np.all(np.isfinite(g)) and margin >= 0
            rows[label] = {
                "J_rel_err": abs(v - ref[0]) / abs(ref[0]) if ok else None,
                "grad_rel_err": float(np.linalg.norm(g - ref[1]) / np.linalg.norm(ref[1]))
                if ok else None,
                "grad_cosine": float(g @ ref[1] / np.linalg.norm(g) / np.linalg.norm(ref[1]))
                if ok else None,
                "wall_s": wall, "barrier_depth": (span - margin) / span,
                "through_barrier": margin < 0}
            print(f"{name:<28}{label:<36}" + ", ".join(
                f"{k} {val:.3g}" for k, val in rows[label].items()
                if isinstance(val, float)), flush=True)
        report["scenes"][name] = {"verlet_dt_s": dt * 1e-3, "configs": rows}
        report["load_average_end"] = os.getloadavg()
        (args.out / "bench_contact_step.json").write_text(json.dumps(report, indent=1))
    return 0


# --- per-step profile (--profile) ----------------------------------------------------------


def timed(fn, *args, repeats: int = 3) -> dict:
    """Best-of-`repeats` wall and process CPU seconds of `fn(*args)` (compiled on a first call
    that is not counted)."""
    import jax

    jax.block_until_ready(fn(*args))
    wall, cpu = [], []
    for _ in range(repeats):
        w0, c0 = time.perf_counter(), time.process_time()
        jax.block_until_ready(fn(*args))
        wall.append(time.perf_counter() - w0)
        cpu.append(time.process_time() - c0)
    return {"wall_s": min(wall), "cpu_s": min(cpu)}


def profile(scene, dt: float, repeats: int) -> dict:
    """Per-step cost of the Verlet solve on `scene` at step `dt` (ms), forward and value-and-
    gradient, with and without contact, float64 and float32, beside the pieces of a step: the
    force evaluation alone (and the energy alone) in a loop, the loop's own cost per iteration,
    the solve without its work-energy ledger and with recomputation (`remat`) in the reverse
    pass, XLA's flop count and transcendental operations of one force evaluation, and the cost
    of those operations per element."""
    import jax
    import jax.numpy as jnp

    from design_engine.physics.dynamics import make_dynamics_args, make_full_state
    from design_engine.physics.energy import make_energy
    from design_engine.physics.geometry import block_geometry
    from design_engine.physics.loading import make_prescribed
    from design_engine.solve import fixed_step
    from design_engine.solve.fixed_step import FixedStepVerlet, step_grid
    from design_engine.solve.objectives import region_energy
    from design_engine.solve.simulate import SolverConfig, make_simulator

    n_steps = step_grid(scene.sample_times, dt).n_steps
    ids = np.asarray(next(iter(scene.targets.values())))
    ts = jnp.asarray(scene.sample_times)
    out = {"dt_s": dt * 1e-3, "steps": n_steps, "bonds": int(scene.lattice.bond_blocks.shape[0]),
           "free_dofs": int(scene.supports.free.size), "solves": {}, "pieces": {}}

    def solve_programs(cfg):
        sim = make_simulator(scene.lattice, scene.supports, cfg, scene.sample_times)

        def f(x):
            return region_energy(sim(x, scene.material, scene.loading, ts), ids)

        return jax.jit(f), jax.jit(jax.value_and_grad(f))

    def row(label, cfg):
        fwd, vg = solve_programs(cfg)
        x = jnp.asarray(scene.design)
        r = {}
        for mode, fn in (("forward", fwd), ("value_and_grad", vg)):
            t = timed(fn, x, repeats=repeats)
            r[mode] = t | {"us_per_step_wall": t["wall_s"] / n_steps * 1e6,
                           "us_per_step_cpu": t["cpu_s"] / n_steps * 1e6}
        mem = vg.lower(x).compile().memory_analysis()
        r["value_and_grad_temp_bytes"] = getattr(mem, "temp_size_in_bytes", None)
        out["solves"][label] = r
        print(f"  {label:<34} forward {r['forward']['us_per_step_cpu']:7.1f} us/step cpu "
              f"({r['forward']['us_per_step_wall']:7.1f} wall), value+grad "
              f"{r['value_and_grad']['us_per_step_cpu']:7.1f} cpu "
              f"({r['value_and_grad']['us_per_step_wall']:7.1f} wall)", flush=True)

    verlet = FixedStepVerlet(max_dt=dt)
    for contact in (True, False):
        for dtype in ("float64", "float32"):
            row(f"{'contact' if contact else 'no contact'} {dtype}",
                SolverConfig(solver=verlet, use_contact=contact, dtype=dtype))
    row("contact float64, remat", SolverConfig(
        solver=FixedStepVerlet(max_dt=dt, remat=True)))
    # the ledger's share: the same solve with its account left unchanged at every step
    # (measurement only: `energy_error` is then 0)
    keep = fixed_step.ledger_step
    fixed_step.ledger_step = lambda led, *rest: led
    try:
        row("contact float64, no ledger", SolverConfig(solver=verlet))
    finally:
        fixed_step.ledger_step = keep

    # the pieces of one step, each in a loop of `n` iterations
    sup = scene.supports
    free, constrained = np.asarray(sup.free), np.asarray(sup.constrained)
    full = make_full_state(sup)
    _, prescribed = make_prescribed(sup)
    args = make_dynamics_args(scene.lattice, sup, block_geometry(scene.lattice, jnp.asarray(
        scene.design)), scene.material, scene.loading)
    q0 = jnp.zeros(free.size)
    n = 2000
    for contact in (True, False):
        energy_fn = make_energy(scene.lattice, use_contact=contact, model=scene.model)

        def energy(qf, t, energy_fn=energy_fn):
            return energy_fn(full(qf, t, args.loading), args.bonds, args.material)

        def force(qf, t, energy_fn=energy_fn):
            potential, grad = jax.value_and_grad(
                lambda q: energy_fn(q, args.bonds, args.material))(full(qf, t, args.loading))
            grad = grad.reshape(-1)
            return -grad[free], potential + jnp.dot(grad[constrained],
                                                    prescribed(t, args.loading)[1])

        kinds = {"energy": lambda c, t: energy(c, t) * jnp.ones_like(c),
                 "force": lambda c, t: force(c, t)[0]}
        if contact:
            kinds["empty loop"] = lambda c, t: c * t
        for kind, body_fn in kinds.items():
            def loop(q, body_fn=body_fn):
                def body(c, k):
                    return c + 1e-9 * body_fn(c, 20.0 + 1e-3 * k), None

                return jax.lax.scan(body, q, jnp.arange(n, dtype=q.dtype))[0]

            t = timed(jax.jit(loop), q0, repeats=repeats)
            label = f"{kind}, {'contact' if contact else 'no contact'}"
            out["pieces"][label] = {"us_per_iteration_cpu": t["cpu_s"] / n * 1e6,
                                    "us_per_iteration_wall": t["wall_s"] / n * 1e6}
            print(f"  {label:<34} {t['cpu_s'] / n * 1e6:7.1f} us/iteration cpu", flush=True)
        compiled = jax.jit(lambda q, force=force: force(q, jnp.asarray(20.0))).lower(q0).compile()
        cost = compiled.cost_analysis()
        cost = cost[0] if isinstance(cost, list) else cost
        text = compiled.as_text()
        out["pieces"][f"force HLO, {'contact' if contact else 'no contact'}"] = {
            "flops": cost.get("flops"), "transcendentals": cost.get("transcendentals"),
            "bytes_accessed": cost.get("bytes accessed"),
            "ops": {op: text.count(f" {op}(") for op in ("cosine", "sine", "atan2", "sqrt",
                                                         "remainder", "divide", "scatter",
                                                         "while", "fusion")}}

    # what the elementwise operations of a force evaluation cost, per element
    per = {}
    m = 4 * out["bonds"]
    for name, op in {"multiply-add": lambda c: c * 1.0001 + 0.5, "cos": jnp.cos,
                     "atan2": lambda c: jnp.arctan2(c, 1.0 + c), "sqrt": lambda c: jnp.sqrt(1.0 + c * c),
                     "remainder": lambda c: jnp.mod(c + np.pi, 2 * np.pi) - np.pi,
                     "divide": lambda c: 1.0 / (2.0 + c)}.items():
        def loop(x, op=op):
            return jax.lax.scan(lambda c, k: (c + 1e-7 * op(c), None), x, jnp.arange(n))[0]

        x = jnp.asarray(np.random.default_rng(0).uniform(-0.3, 0.3, m))
        per[name] = timed(jax.jit(loop), x, repeats=repeats)["cpu_s"] / n / m * 1e9
    out["ns_per_element_float64"] = per
    print("  ns per element (float64): " + ", ".join(f"{k} {v:.2f}" for k, v in per.items()),
          flush=True)
    return out


if __name__ == "__main__":
    raise SystemExit(main())
