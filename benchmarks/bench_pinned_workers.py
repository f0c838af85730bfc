"""Sweep workers on one core each, or on every core: what a fixed step costs either way.

XLA's CPU runtime sizes its thread pool by the cores a process may use and forks its larger
loops over them, waking the other core for each. A sweep's local workers are single-threaded
(one evaluation at a time each), so `design_engine.sweeps.distributed` runs worker N on core N
(`cores.pin_to_one_core`). This times the protection scene's forward solve (24x18 at 8 %, the
policy's configuration, from the static equilibrium, over its first --samples sample times)
in fresh processes that start as a local worker does (its environment and XLA_FLAGS): one
process alone, and two at once, each either free to use every core or pinned to a core of its
own by `pin_to_one_core`; the four cases alternate for --rounds rounds so that a change of
load hits them all. Per process: microseconds per step, best and median of --repeats solves.
The compiled program comes from one compilation cache, filled by a first process. Writes
OUT/NAME.json (default benchmarks/results/bench_pinned_workers.json).

    .venv/bin/python benchmarks/bench_pinned_workers.py [--rounds 2] [--repeats 7]
        [--samples 80] [--out benchmarks/results] [--name bench_pinned_workers]
"""

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from machine import describe, source_checkout

ROOT = Path(__file__).resolve().parent.parent

CHILD = """
import json, sys, time
pin, samples, repeats = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])
from metarig.cores import pin_to_one_core
core = pin_to_one_core(pin) if pin >= 0 else None  # before XLA starts
import jax
sys.path.insert(0, "benchmarks")
from protection_forward import protection_forward
solve, x, q_s, steps, _ = protection_forward(samples)
jax.block_until_ready(solve(x, q_s))
sys.stdout.write("ready\\n"); sys.stdout.flush()
sys.stdin.readline()  # both processes of a pair start timing together
seconds = []
for _ in range(repeats):
    t0 = time.perf_counter()
    jax.block_until_ready(solve(x, q_s))
    seconds.append(time.perf_counter() - t0)
print(json.dumps({"core": core, "steps": steps, "us_per_step_best": min(seconds) / steps * 1e6,
                  "us_per_step_median": sorted(seconds)[len(seconds) // 2] / steps * 1e6}))
"""


def child_env(cache: str) -> dict:
    """A local sweep worker's environment (`distributed.worker_environment`, its XLA_FLAGS)."""
    from design_engine.sweeps.distributed import worker_environment, worker_xla_flags

    return {**os.environ, **worker_environment(), "XLA_FLAGS": worker_xla_flags(),
            "METARIG_JAX_CACHE": cache, "METARIG_JAX_CACHE_MIN_S": "0"}


def run_case(pins: list[int], samples: int, repeats: int, env: dict) -> list[dict]:
    """Processes pinned by `pins` (-1: every core), started together; their rows."""
    procs = [subprocess.Popen([sys.executable, "-c", CHILD, str(p), str(samples), str(repeats)],
                              env=env, cwd=ROOT, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                              text=True) for p in pins]
    for p in procs:
        if p.stdout.readline().strip() != "ready":
            raise SystemExit(f"a timing process failed (exit {p.wait()})")
    for p in procs:
        p.stdin.write("go\n")
        p.stdin.flush()
    rows = []
    for p in procs:
        out, _ = p.communicate()
        if p.returncode != 0:
            raise SystemExit(f"a timing process failed (exit {p.returncode})")
        rows.append(json.loads(out.strip().splitlines()[-1]))
    return rows


CASES = {"alone, every core": [-1], "alone, one core": [0],
         "two at once, every core": [-1, -1], "two at once, one core each": [0, 1]}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rounds", type=int, default=2)
    p.add_argument("--repeats", type=int, default=7)
    p.add_argument("--samples", type=int, default=80)
    p.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results")
    p.add_argument("--name", default="bench_pinned_workers")
    args = p.parse_args(argv)
    for name in ("rounds", "repeats", "samples"):
        if getattr(args, name) < (2 if name == "samples" else 1):
            p.error(f"--{name} is too small: {getattr(args, name)}")
    result = {"machine": describe(), "source": source_checkout(),
              "load_average_1min": {"start": os.getloadavg()[0]},
              "scene": "protection-24x18 at 8 %, the policy's configuration, forward solve",
              "samples": args.samples, "repeats": args.repeats, "cases": {k: [] for k in CASES}}
    with tempfile.TemporaryDirectory() as cache:
        env = child_env(cache)
        run_case([-1], args.samples, 1, env)  # compiles into the cache
        for r in range(args.rounds):
            for case, pins in CASES.items():
                print(f"round {r + 1}/{args.rounds}: {case} ...", flush=True)
                result["cases"][case].append(run_case(pins, args.samples, args.repeats, env))
    result["load_average_1min"]["end"] = os.getloadavg()[0]

    def median_of(case):
        return statistics.median(row["us_per_step_median"] for rnd in result["cases"][case]
                                 for row in rnd)

    result["median_us_per_step"] = {case: round(median_of(case), 1) for case in CASES}
    result["ratio_one_core_to_every_core"] = {
        "alone": round(median_of("alone, one core") / median_of("alone, every core"), 3),
        "two at once": round(median_of("two at once, one core each")
                             / median_of("two at once, every core"), 3)}
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / f"{args.name}.json"
    path.write_text(json.dumps(result, indent=1))
    for case, us in result["median_us_per_step"].items():
        print(f"{case:28s} {us:7.1f} us a step (median over processes and rounds)")
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
