"""Robustness map of the optimised 24x16 focusing design: batched (jax.vmap) against a loop of
single simulations, side by side in one process, with agreement of the ratios.

The design is `benchmarks/results/design_focusing-24x16.json` (the focusing benchmark's
result). Both ways use the same solver policy (`robustness.evaluate_points`: the automatic
configuration, re-solved with contact where voids reach the cutoff); the batched way solves
`--chunk` points per compiled call, the loop one point per call. Wall times include each way's
own compilation (reported separately too). Writes benchmarks/results/bench_robustness.json.

    .venv/bin/python benchmarks/bench_robustness.py [--frequencies 20,35,55] [--amplitudes 0.1,0.5,0.9]
"""

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--design", type=Path,
                   default=ROOT / "benchmarks/results/design_focusing-24x16.json")
    p.add_argument("--frequencies", default="20,35,55", help="Hz")
    p.add_argument("--amplitudes", default="0.1,0.3,0.5,0.7", help="units of the spacing s")
    p.add_argument("--chunk", type=int, default=4, help="points per batch of the batched way")
    p.add_argument("--out", type=Path, default=ROOT / "benchmarks/results/bench_robustness.json")
    args = p.parse_args(argv)

    from design_engine.design.design_io import load_design
    from design_engine.sweeps import robustness as rb

    lattice, design_mm = load_design(args.design)
    scene = rb.design_scene(design_mm / 1e3, lattice.describe())
    s_m = scene.lattice.spacing / 1e3
    freqs = np.array([float(v) for v in args.frequencies.split(",")])
    amps = np.array([float(v) for v in args.amplitudes.split(",")]) * s_m
    pts = rb.grid_points(freqs, amps)
    f_min = float(freqs.min())
    chunk = args.chunk
    load0 = os.getloadavg()

    def timed(fn):
        t0 = time.perf_counter()
        out = fn()
        return out, time.perf_counter() - t0

    # warm-up of each way on one chunk / one point: its compilation, measured on its own
    _, compile_batched = timed(lambda: rb.evaluate_points(scene, pts[:chunk], f_min_hz=f_min,
                                                          chunk=chunk))
    _, compile_single = timed(lambda: rb.evaluate_points(scene, pts[:1], f_min_hz=f_min,
                                                         chunk=1))
    batched, wall_b = timed(lambda: rb.evaluate_points(scene, pts, f_min_hz=f_min, chunk=chunk))
    loop = []
    t0 = time.perf_counter()
    for k, pt in enumerate(pts):
        loop.append(rb.evaluate_points(scene, pt[None], f_min_hz=f_min, chunk=1))
        print(f"loop: point {k + 1}/{len(pts)}", flush=True)
    wall_l = time.perf_counter() - t0
    r_b = np.asarray(batched["ratio"])
    r_l = np.array([r["ratio"][0] for r in loop])
    rel = np.abs(r_b - r_l) / np.abs(r_l)
    report = {
        "design": str(args.design.relative_to(ROOT) if args.design.is_relative_to(ROOT)
                      else args.design),
        "lattice": list(scene.lattice.shape), "points": int(len(pts)),
        "frequencies_hz": freqs.tolist(), "amplitudes_m": amps.tolist(), "chunk": chunk,
        "batched_s": wall_b, "loop_s": wall_l, "ratio_loop_over_batched": wall_l / wall_b,
        "first_call_s": {"batched (one chunk, compile included)": compile_batched,
                         "single (one point, compile included)": compile_single},
        "solvers_batched": [c["solver"]["solver"] for c in batched["configs"]],
        "points_resolved_with_contact": int(sum(c > 0 for c in batched["config"])),
        "max_rel_diff_R": float(np.nanmax(rel)), "R": r_b.tolist(),
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(),
                    "load_before": load0, "load_after": os.getloadavg()},
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2) + "\n")
    print(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
