"""`metarig bench work-precision | speedup`: the speed-accuracy studies of the engine."""

import argparse
import json
import logging
import sys
from pathlib import Path


def bench_main(argv: list[str] | None = None) -> int:
    """Speed against accuracy: work-precision charts, throughput and the side-by-side speed-up."""
    p = argparse.ArgumentParser(prog="metarig bench", description=bench_main.__doc__)
    sub = p.add_subparsers(dest="study", required=True)
    wp = sub.add_parser("work-precision", help="error vs wall time for every method, both scenes")
    wp.add_argument("--out", type=Path, default=Path("runs/bench"))
    wp.add_argument("--quick", action="store_true", help="three methods only (smoke run)")
    wp.add_argument("--scene", action="append", help="limit to these study scenes")
    wp.add_argument("--implicit", action="store_true", help="also run diffrax's Kvaerno5 "
                    "(dense Newton solves; very slow here)")
    st = sub.add_parser("stability", help="where methods break: step, amplitude, pre-compression")
    st.add_argument("--out", type=Path, default=Path("runs/bench"))
    st.add_argument("--contact", action="store_true",
                    help="the contact scenes instead: the default policy against a tight "
                         "reference over strain to 9 %%, amplitude and fixed steps with contact")
    tp = sub.add_parser("throughput", help="vmap batch cost per design; first-call compile time")
    tp.add_argument("--out", type=Path, default=Path("runs/bench"))
    sp = sub.add_parser("speedup", help="default vs baseline value-and-gradient, side by side")
    sp.add_argument("--out", type=Path, default=Path("runs/bench"))
    sp.add_argument("--repeats", type=int, default=3)
    sp.add_argument("--scene", default="focusing-24x16",
                    help="study scene: focusing-24x16 (default), focusing-contact-24x16, "
                         "precompressed-contact-12x10, focus-vs-protect-24x18, "
                         "reprogram-location-24x18")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    import design_engine  # noqa: F401
    from metarig.readback import DamagedFileError

    if args.study == "work-precision":
        from design_engine.studies.work_precision import (SCENES, fastest_acceptable, plot_study,
                                                          run_study)

        unknown = set(args.scene or []) - set(SCENES)
        if unknown:
            print(f"metarig bench: unknown scene(s) {sorted(unknown)}; choose from {list(SCENES)}",
                  file=sys.stderr)
            return 2
        try:
            results = run_study(args.out, quick=args.quick, scenes=args.scene,
                                implicit=args.implicit)
        except KeyboardInterrupt:
            print("interrupted: finished methods are kept in work_precision.json; rerun to resume")
            return 130
        except DamagedFileError as exc:
            print(f"metarig bench: error: {exc}", file=sys.stderr)
            return 2
        charts = plot_study(results, args.out)
        best = fastest_acceptable(results)
        summary = {"charts": [c.name for c in charts],
                   "fastest_acceptable": best[0] if best else None}
        (args.out / "work_precision_summary.json").write_text(json.dumps(summary, indent=2))
        print(json.dumps(summary, indent=2))
        return 0
    if args.study == "stability" and args.contact:
        from design_engine.studies.stability import run_contact_stability

        r = run_contact_stability(args.out)
        for part, key in (("strain", "strain"), ("amplitude", "amplitude_m")):
            for row in r[part]["rows"]:
                pol = row["policy"]
                print(f"{key} {row[key]:g}: " + (f"{pol['config']}, {pol['solves']} solve(s), "
                      + (f"J error {row['J_rel_err']:.2e}" if "J_rel_err" in row else
                         f"reference: {row['reference'].get('error')}")
                      if pol["ok"] else pol["error"]))
        print(f"wrote {args.out / 'stability_contact.json'} and stability_contact.png")
        return 0
    if args.study == "stability":
        from design_engine.studies.stability import run_stability

        r = run_stability(args.out)
        for row in r["step_vs_limit"]["rows"]:
            print(f"dt/limit {row['dt_over_limit']:.2f}: "
                  + (f"J error {row['J_rel_err']:.2e}" if row["ok"] else row["error"]))
        print(f"wrote {args.out / 'stability.json'} and stability.png")
        return 0
    if args.study == "throughput":
        from design_engine.studies.throughput import run_throughput

        r = run_throughput(args.out)
        for row in r["batches"]:
            print(f"batch {row['batch']:>3}: {row['per_design_s']:.3f} s per design")
        print(f"first value-and-gradient call: {r['value_and_grad_first_call']}")
        return 0
    from design_engine.studies.speedup import SCENES, run_speedup

    if args.scene not in SCENES:
        print(f"metarig bench speedup: unknown scene {args.scene!r}; choose from "
              f"{', '.join(SCENES)}", file=sys.stderr)
        return 2
    if args.repeats < 1:
        print("metarig bench speedup: --repeats must be at least 1", file=sys.stderr)
        return 2
    try:
        r = run_speedup(args.out, scene=args.scene, repeats=args.repeats)
    except KeyboardInterrupt:
        print("interrupted: the tight reference, once computed, is kept in --out; rerun to resume")
        return 130
    except DamagedFileError as exc:
        print(f"metarig bench: error: {exc}", file=sys.stderr)
        return 2
    print(f"value-and-gradient, {args.scene}: baseline {r['baseline_s']:.2f} s, default "
          f"{r['default_s']:.2f} s, ratio {r['ratio']:.1f}x; default vs reference: J "
          f"{r['J_rel_err']:.2e}, gradient {r['grad_rel_err']:.2e} (cosine {r['grad_cosine']:.6f})")
    name = "speedup.json" if args.scene == "focusing-24x16" else f"speedup_{args.scene}.json"
    print(f"wrote {args.out / name}")
    return 0
