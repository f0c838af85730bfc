"""Where two design runs from the same start part: per evaluation, how far each run's design and
gradient are from a reference run's (its `checkpoint.npz`).

For the runs of `bench_design_contact.py` (OUT/<label>/ folders): for every run other than
`--against` (default `baseline`) and each evaluation k both hold, the largest difference of the
free design variables (mm), the relative difference of the gradients |g - g_ref| / |g_ref|
and their cosine, and the relative difference of the objectives. Tells whether two runs' designs
differ because their solves disagree (the gradients differ at the same design) or because the
optimiser amplified an earlier difference (the designs differ). Writes OUT/<name>_paths.json
and copies it to benchmarks/results/.

    .venv/bin/python benchmarks/bench_design_paths.py runs/bench-design-contact-focusing \
        [--against baseline] [--evals 12] [--name bench_design_contact_focusing]
"""

import argparse
import json
import shutil
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent


def paths(out: Path, against: str, evals: int) -> dict:
    """{label: [{eval, max_dx_mm, grad_rel_diff, grad_cosine, objective_rel_diff}, ...]}."""
    ref = np.load(out / against / "checkpoint.npz")
    result = {}
    for folder in sorted(p.parent for p in out.glob("*/checkpoint.npz")):
        if folder.name == against:
            continue
        run = np.load(folder / "checkpoint.npz")
        n = min(evals, len(run["f"]), len(ref["f"]))
        rows = []
        for k in range(n):
            g, g0 = run["grad"][k], ref["grad"][k]
            rows.append({
                "eval": k + 1,
                "max_dx_mm": float(np.abs(run["x"][k] - ref["x"][k]).max()),
                "grad_rel_diff": float(np.linalg.norm(g - g0) / np.linalg.norm(g0)),
                "grad_cosine": float(g @ g0 / (np.linalg.norm(g) * np.linalg.norm(g0))),
                "objective_rel_diff": float(abs(run["f"][k] - ref["f"][k]) / abs(ref["f"][k])),
            })
        result[folder.name] = rows
    return result


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("out", type=Path, help="a bench_design_contact.py output folder")
    p.add_argument("--against", default="baseline", help="the reference run's folder name")
    p.add_argument("--evals", type=int, default=12, help="the first N evaluations")
    p.add_argument("--name", help="results name (default: the report's in OUT)")
    args = p.parse_args(argv)
    if not (args.out / args.against / "checkpoint.npz").exists():
        raise SystemExit(f"no run {args.against!r} in {args.out}")
    name = args.name or next((f.stem for f in sorted(args.out.glob("bench_design_contact*.json"))
                              if not f.stem.endswith("_paths")), "bench_design_contact")
    report = {"against": args.against, "runs": paths(args.out, args.against, args.evals)}
    path = args.out / f"{name}_paths.json"
    path.write_text(json.dumps(report, indent=2))
    shutil.copy(path, HERE / "results" / path.name)
    for label, rows in report["runs"].items():
        print(f"{label} against {args.against}:")
        for r in rows:
            print(f"  {r['eval']:3d}  dx {r['max_dx_mm']:.2e} mm  gradient {r['grad_rel_diff']:.2e}"
                  f" (cosine {r['grad_cosine']:.7f})  objective {r['objective_rel_diff']:.1e}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
