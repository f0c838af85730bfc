"""XLA's CPU code generators side by side: the new fusion emitters (XLA's default) against the
classic ones (`--xla_cpu_use_fusion_emitters=false`, which `design_engine` sets unless told
otherwise), on the engine's programs as a user runs them. Writes
benchmarks/results/bench_xla_emitters.json.

    .venv/bin/python benchmarks/bench_xla_emitters.py [--repeats 2] [--out FILE]

Each case runs in a fresh process with the compilation cache off, so the first call pays
tracing + compilation + the solve; "steady" is the median of three further calls (the compiled
program only). "compile_s" sums XLA's own compilation times (JAX's compile log). The two
settings alternate (A B A B ...) so that a change of load hits both; the load average is
recorded before and after.
"""

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from machine import describe

ROOT = Path(__file__).resolve().parent.parent
# explicit both ways: design_engine adds the classic setting to XLA_FLAGS when they name neither
SETTINGS = {"fusion emitters (XLA's default)": "--xla_cpu_use_fusion_emitters=true",
            "classic emitters (metarig's default)": "--xla_cpu_use_fusion_emitters=false"}

# one case per program kind the engine compiles: (name, code building `call`, a no-arg callable
# returning a number to print)
CASES = {
    "pulse 24x16, default policy (Verlet)": """
scene = build_scene("focusing-24x16")
call = lambda: simulate_scene(scene).metrics["target_ke_mean_J"]
""",
    "value and gradient 8x6, Dopri8 with contact": """
scene = build_scene("focusing-24x16", nx=8, ny=6, amplitude_m=2e-3)
cfg = contact_config()
vg, _ = make_objective(scene, cfg)
x = jnp.asarray(scene.design)
call = lambda: float(checked(vg(x), cfg)[0][0])
""",
    "default experiment 24x16 at 2 % (static start + pulse)": """
scene = build_scene("precompression-24x18", nx=24, ny=16, strain=0.02)
call = lambda: simulate_scene(scene).metrics["target_ke_mean_J"]
""",
}

CHILD = """
import json, logging, re, statistics, sys, time
compile_s = [0.0]
class _Log(logging.Handler):
    def emit(self, record):
        m = re.search(r"Finished XLA compilation .* in ([0-9.]+) sec", record.getMessage())
        if m:
            compile_s[0] += float(m[1])
import jax
jax.config.update("jax_log_compiles", True)
_lg = logging.getLogger("jax._src.dispatch"); _lg.addHandler(_Log()); _lg.propagate = False
import jax.numpy as jnp
import design_engine
from design_engine.physics.scenes import build_scene
from design_engine.solve.policy import contact_config
from design_engine.solve.run import checked, make_objective, simulate_scene
%s
t = time.perf_counter(); value = call(); first = time.perf_counter() - t
steady = []
for _ in range(3):
    t = time.perf_counter(); call(); steady.append(time.perf_counter() - t)
print(json.dumps({"first_s": first, "compile_s": compile_s[0],
                  "steady_s": statistics.median(steady), "value": value}))
"""


def run_case(code: str, flags: str) -> dict:
    env = dict(os.environ, METARIG_JAX_CACHE="", XLA_FLAGS=flags)
    out = subprocess.run([sys.executable, "-c", CHILD % code], env=env, cwd=ROOT,
                         capture_output=True, text=True)
    if out.returncode != 0:
        raise SystemExit(f"bench_xla_emitters: case failed:\n{out.stderr[-2000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=2, help="runs of each case and setting")
    parser.add_argument("--out", type=Path,
                        default=ROOT / "benchmarks/results/bench_xla_emitters.json")
    args = parser.parse_args(argv)
    load_before = os.getloadavg()[0]
    cases = {}
    try:
        for name, code in CASES.items():
            runs = {label: [] for label in SETTINGS}
            for r in range(args.repeats):
                for label, flags in SETTINGS.items():
                    res = run_case(code, flags)
                    runs[label].append(res)
                    print(f"[{name}] {label} #{r + 1}: first {res['first_s']:.2f} s "
                          f"(compile {res['compile_s']:.2f} s), steady {res['steady_s']:.3f} s, "
                          f"value {res['value']:.12g}", flush=True)
            cases[name] = runs
    except KeyboardInterrupt:
        print("bench_xla_emitters: interrupted; writing the cases finished so far", file=sys.stderr)
    summary = {}
    for name, runs in cases.items():
        new, old = (runs[label] for label in SETTINGS)
        if not new or not old:
            continue
        best = {k: (min(r[k] for r in new), min(r[k] for r in old))
                for k in ("first_s", "compile_s", "steady_s")}
        summary[name] = {f"{k}_ratio_classic_over_fusion": round(b / a, 3)
                         for k, (a, b) in best.items()}
        summary[name]["value_rel_diff"] = abs(old[0]["value"] - new[0]["value"]) / max(
            abs(new[0]["value"]), 1e-300)
    result = {"machine": describe(), "load_average_1min": {
        "before": round(load_before, 2), "after": round(os.getloadavg()[0], 2)},
        "date": time.strftime("%Y-%m-%d %H:%M", time.gmtime()) + " UTC",
        "settings": SETTINGS, "runs": cases, "summary": summary}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    for name, s in summary.items():
        print(f"{name}: {s}")
    print(f"-> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
