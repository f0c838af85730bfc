"""Time per evaluation of the two reprogrammable pairs, before and after issue 12, side by side.

"Before" is the default the engine had for pre-compressed scenes until then: adaptive Dopri8 at
the reference tolerances (rtol 1e-8, atol 1e-4) with contact, through the dynamic
pre-compression ramp. "After" is today's default: the automatic policy on the static
pre-compression (`run.make_objective(scene)`). Both are value-and-gradient of the periodic
design, each term of the pair (focus-vs-protect-24x18: 1 % and 8 %; reprogram-location-24x18:
2 % and 5 %), compile excluded, in one run. Writes
benchmarks/results/bench_contact_before_after.json.

    .venv/bin/python benchmarks/bench_contact_before_after.py [--repeats 1] [--pairs focus-vs-protect-24x18,...]
"""

import argparse
import json
import os
import platform
from pathlib import Path

HERE = Path(__file__).resolve().parent
PAIRS = ("focus-vs-protect-24x18", "reprogram-location-24x18")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repeats", type=int, default=1, help="warm calls of the slow 'before' "
                   "configuration (the default gets 3)")
    p.add_argument("--pairs", default=",".join(PAIRS), help="comma-separated, from: "
                   + ", ".join(PAIRS))
    p.add_argument("--out", type=Path, default=HERE / "results" / "bench_contact_before_after.json")
    args = p.parse_args(argv)

    import jax.numpy as jnp

    from design_engine.solve.policy import contact_config
    from design_engine.solve.run import make_objective
    from design_engine.studies.speedup import SCENES, term_scene, timed_value_and_grad

    report = {"before": "Dopri8, rtol 1e-8, atol 1e-4, with contact, float64, dynamic ramp",
              "after": "automatic policy, static pre-compression",
              "machine": {"platform": platform.platform(), "cpus": os.cpu_count(),
                          "load_before": os.getloadavg()}, "pairs": {}}
    pairs = [q for q in args.pairs.split(",") if q]
    if set(pairs) - set(PAIRS):
        raise SystemExit(f"unknown pairs {sorted(set(pairs) - set(PAIRS))}; choose from {PAIRS}")
    for pair in pairs:
        rows = []
        for term in SCENES[pair]:
            label = f"{pair}, strain {term.scene['strain']:g}"
            ramp, static = term_scene(term, "ramp"), term_scene(term)
            print(f"{label}: before ...", flush=True)
            vg, _ = make_objective(ramp, contact_config())
            before = timed_value_and_grad(vg, jnp.asarray(ramp.design), contact_config(),
                                          args.repeats)
            print(f"{label}: after ...", flush=True)
            vg, _ = make_objective(static)
            after = timed_value_and_grad(vg, jnp.asarray(static.design), None, 3)
            rows.append({"strain": term.scene["strain"], "before_s": before[0],
                         "after_s": after[0], "ratio": before[0] / after[0]})
            print(f"{label}: before {before[0]:.1f} s, after {after[0]:.2f} s, "
                  f"{before[0] / after[0]:.1f}x", flush=True)
        total_b, total_a = sum(r["before_s"] for r in rows), sum(r["after_s"] for r in rows)
        report["pairs"][pair] = {"terms": rows, "before_s": total_b, "after_s": total_a,
                                 "ratio": total_b / total_a}
        args.out.write_text(json.dumps(report, indent=2))
    report["machine"]["load_after"] = os.getloadavg()
    args.out.write_text(json.dumps(report, indent=2))
    for pair, r in report["pairs"].items():
        print(f"{pair}: before {r['before_s']:.1f} s, after {r['after_s']:.2f} s per "
              f"evaluation, {r['ratio']:.1f}x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
