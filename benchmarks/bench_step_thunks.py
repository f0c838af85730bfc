"""What a fixed step runs, kernel by kernel: XLA's CPU runtime executes a compiled program as a
sequence of kernels ("thunks": fused loops, copies, scatter loops, ...), each with a cost of its
own beyond its arithmetic. This profiles the forward solve of the protection scene (24x18 at
8 %, the policy's configuration: Verlet with contact and contact substeps, from the static
equilibrium) over its first `--samples` sample times with `jax.profiler.trace(...,
create_perfetto_trace=True)` and reads the trace back: per step, how many thunks of each kind
ran and their own profiled microseconds (less the thunks nested in them, as a loop's body is in
its loop; the profiler adds its own cost to each thunk, so these overstate the time), the costliest thunks, and the same solve's unprofiled time per step (best
of 3). Writes OUT/NAME.json (default bench_step_thunks.json). Run from another checkout's
source to profile its code with this script (`git worktree add DIR REF`, then
`PYTHONPATH=DIR python benchmarks/bench_step_thunks.py`: the file records which
`design_engine` it profiled, `source`).

    .venv/bin/python benchmarks/bench_step_thunks.py --out benchmarks/results
"""

import argparse
import collections
import gzip
import json
import os
import re
import tempfile
import time
from pathlib import Path

from machine import describe, source_checkout

# the runtime's own spans, around the thunks
RUNTIME = re.compile(r"^(ThunkExecutor|\$|PjitFunction|CommonPjRt|end: )")


def kind(name: str) -> str:
    """A thunk's kind from its HLO name: fusion, copy, call (XLA's scatter loops and other
    small calls), while, or the operation's own name."""
    base = re.sub(r"\.\d+$", "", name)
    if base.endswith("fusion"):
        return "fusion"
    return base


def exclusive(spans: list[dict]) -> list[float]:
    """Each span's own microseconds: its duration less that of the spans nested in it on the
    same thread (a loop's span holds its body's thunks)."""
    own = [float(e.get("dur", 0.0)) for e in spans]
    for tid in {e.get("tid") for e in spans}:
        order = sorted((k for k, e in enumerate(spans) if e.get("tid") == tid),
                       key=lambda k: (spans[k]["ts"], -spans[k].get("dur", 0.0)))
        stack: list[int] = []
        for k in order:
            start = spans[k]["ts"]
            while stack and start >= spans[stack[-1]]["ts"] + spans[stack[-1]].get("dur", 0.0):
                stack.pop()
            if stack:
                own[stack[-1]] -= spans[k].get("dur", 0.0)
            stack.append(k)
    return own


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=Path("runs/bench-step-thunks"))
    p.add_argument("--name", default="bench_step_thunks", help="output file name, no suffix")
    p.add_argument("--samples", type=int, default=40, help="sample times solved through")
    args = p.parse_args(argv)
    if args.samples < 2:
        p.error(f"--samples must be at least 2, got {args.samples}")

    import jax

    from protection_forward import protection_forward

    solve, x, q_s, steps, config = protection_forward(args.samples)
    solve = solve.lower(x, q_s).compile()
    jax.block_until_ready(solve(x, q_s))
    best = float("inf")
    for _ in range(3):
        t0 = time.perf_counter()
        jax.block_until_ready(solve(x, q_s))
        best = min(best, time.perf_counter() - t0)
    load0 = os.getloadavg()
    with tempfile.TemporaryDirectory() as trace_dir:
        with jax.profiler.trace(trace_dir, create_perfetto_trace=True):
            jax.block_until_ready(solve(x, q_s))
        (trace,) = Path(trace_dir).rglob("perfetto_trace.json.gz")
        events = json.loads(gzip.decompress(trace.read_bytes()))["traceEvents"]
    spans = [e for e in events if e.get("ph") == "X" and not RUNTIME.match(e["name"])]
    count, micros = collections.Counter(), collections.defaultdict(float)
    by_name = collections.defaultdict(float)
    for e, own in zip(spans, exclusive(spans)):
        count[kind(e["name"])] += 1
        micros[kind(e["name"])] += own
        by_name[e["name"]] += own
    report = {
        "machine": describe(), "source": source_checkout(),
        "load_average_start": load0, "load_average_end": os.getloadavg(),
        "scene": "protection-24x18 at 8 %", "config": repr(config), "samples": args.samples,
        "steps": steps, "unprofiled_us_per_step": best / steps * 1e6,
        "thunks_per_step": sum(count.values()) / steps,
        "per_step": {k: {"thunks": count[k] / steps, "profiled_us": micros[k] / steps}
                     for k in sorted(count, key=lambda k: -micros[k])},
        "costliest": [{"thunk": n, "profiled_us_per_step": us / steps}
                      for n, us in sorted(by_name.items(), key=lambda kv: -kv[1])[:15]],
    }
    print(f"{steps} steps, {best / steps * 1e6:.1f} us a step unprofiled, "
          f"{report['thunks_per_step']:.0f} thunks a step:")
    for k, row in list(report["per_step"].items())[:8]:
        print(f"  {k:<12} {row['thunks']:6.1f} a step, {row['profiled_us']:7.1f} us profiled")
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / f"{args.name}.json").write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
