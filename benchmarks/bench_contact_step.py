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

    .venv/bin/python benchmarks/bench_contact_step.py
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


if __name__ == "__main__":
    raise SystemExit(main())
