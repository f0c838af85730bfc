"""Benchmark of the physics core: forward solve and value-and-gradient of the focusing objective.

Sizes 8x6, 16x12, 24x16, 48x32 of the focusing scene (paper pulse, targets kept at the same
relative position), for the automatic default configuration and the full reference model
(Dopri5, spec tolerances). Compile time (first call) is reported separately from the
steady-state median of `--repeats` calls. Writes JSON after every case (interrupt-safe), prints
a table and charts cost against size (bench_core.png).

    .venv/bin/python benchmarks/bench_core.py --out runs/bench
"""

import argparse
import json
import os
import platform
import statistics
import time
from pathlib import Path

from tqdm import tqdm


def _time(fn, repeats: int) -> tuple[float, list[float], object]:
    t0 = time.perf_counter()
    out = fn()
    first = time.perf_counter() - t0
    runs = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        runs.append(time.perf_counter() - t0)
    return first, runs, out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=Path("runs/bench"))
    p.add_argument("--sizes", default="8x6,16x12,24x16,48x32")
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--no-grad", action="store_true", help="forward solves only")
    p.add_argument("--configs", default="auto,full", help="auto (default policy) and/or full")
    args = p.parse_args(argv)

    import jax
    import jax.numpy as jnp

    import design_engine  # noqa: F401
    from design_engine.physics.scenes import build_scene
    from design_engine.solve.run import checked, compiled_simulator, default_choice, make_objective
    from design_engine.solve.simulate import SolverConfig, check_solution

    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "bench_core.json"
    report = {"machine": {"platform": platform.platform(), "cpus": os.cpu_count(),
                          "jax": jax.__version__, "device": str(jax.devices()[0])},
              "cases": []}
    sizes = [tuple(int(v) for v in s.split("x")) for s in args.sizes.split(",")]
    todo = [(c, nx, ny) for c in args.configs.split(",") for nx, ny in sizes]
    try:
        for label, nx, ny in tqdm(todo, desc="cases"):
            scene = build_scene("focusing-24x16", nx=nx, ny=ny)
            config = default_choice(scene).config if label == "auto" else SolverConfig()
            x = jnp.asarray(scene.design)
            ts = jnp.asarray(scene.sample_times)
            sim = compiled_simulator(scene, config)
            def fwd(sim=sim, x=x, scene=scene, ts=ts):
                return jax.block_until_ready(sim(x, scene.material, scene.loading, ts))

            first, runs, sol = _time(fwd, args.repeats)
            check_solution(sol, config)
            case = {"config": label, "size": f"{nx}x{ny}", "n_units": scene.n_units,
                    "n_bonds": scene.lattice.n_bonds,
                    "n_free_dofs": int(scene.supports.free.size),
                    "forward_first_call_s": first, "forward_s": statistics.median(runs),
                    "forward_compile_s": first - statistics.median(runs),
                    "accepted_steps": int(sol.num_accepted), "rejected_steps": int(sol.num_rejected)}
            if not args.no_grad:
                vg, _ = make_objective(scene, config)
                g_first, g_runs, out = _time(lambda vg=vg, x=x: jax.block_until_ready(vg(x)),
                                             args.repeats)
                checked(out, config)
                case.update({"value_and_grad_first_call_s": g_first,
                             "value_and_grad_s": statistics.median(g_runs),
                             "value_and_grad_compile_s": g_first - statistics.median(g_runs),
                             "J_mean_mJ": float(out[0][0]) / scene.n_samples})
            report["cases"].append(case)
            path.write_text(json.dumps(report, indent=2))
    except KeyboardInterrupt:
        print(f"interrupted: {len(report['cases'])} cases kept in {path}")
    path.write_text(json.dumps(report, indent=2))
    _chart(report, args.out / "bench_core.png")
    print(f"\n{'config':>6} {'size':>7} {'units':>6} {'steps':>6} {'fwd [s]':>8} {'fwd compile':>11} "
          f"{'v+g [s]':>8} {'v+g compile':>11}")
    for c in report["cases"]:
        print(f"{c['config']:>6} {c['size']:>7} {c['n_units']:>6} {c['accepted_steps']:>6} "
              f"{c['forward_s']:>8.2f} "
              f"{c['forward_compile_s']:>11.1f} {c.get('value_and_grad_s', float('nan')):>8.2f} "
              f"{c.get('value_and_grad_compile_s', float('nan')):>11.1f}")
    print(f"wrote {path}")
    return 0


def _chart(report: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for label in sorted({c["config"] for c in report["cases"]}):
        rows = [c for c in report["cases"] if c["config"] == label]
        for key, style in (("forward_s", "o-"), ("value_and_grad_s", "s--")):
            if all(key in c for c in rows):
                ax.loglog([c["n_units"] for c in rows], [c[key] for c in rows], style,
                          label=f"{label}: {key.replace('_s', '')}")
    ax.set_xlabel("units")
    ax.set_ylabel("wall time per evaluation [s]")
    ax.set_title("focusing scene: cost against lattice size")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    raise SystemExit(main())
