"""A Pareto front's best designs re-evaluated on the reference model.

The sweep optimises on the default model (static pre-compression, the solver policy). This
re-evaluates the `--top` front points of highest ratio J1/J2 (a protection task: J1 maximised,
J2 minimised) on the reference model: the task's scenes with the dynamic pre-compression ramp,
solved with Dopri8 at the reference tolerances with contact. Writes `--out` (JSON) with, per
point, both models' J1, J2 and ratio.

    .venv/bin/python benchmarks/bench_front_reference.py runs/fvp-front2 --top 3
"""

import argparse
import json
import sys
import tempfile
from pathlib import Path

from tqdm import tqdm

ROOT = Path(__file__).resolve().parents[1]


def ramp_task(source: str, size):
    """The sweep's task with every scene's pre-compression on the dynamic ramp."""
    from design_engine.design.task import load_task, preset_path

    path = Path(source) if Path(source).exists() else preset_path(source)
    text = path.read_text()
    if 'precompression = "static"' not in text:
        raise SystemExit(f"{path}: no static pre-compression to replace")
    with tempfile.TemporaryDirectory() as tmp:
        ramp = Path(tmp) / path.name
        ramp.write_text(text.replace('precompression = "static"', 'precompression = "ramp"'))
        return load_task(ramp, size=size)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("sweep", type=Path, help="sweep folder (front.json, front/, sweep.json)")
    p.add_argument("--top", type=int, default=3, help="front points of highest ratio (default 3)")
    p.add_argument("--out", type=Path, default=None,
                   help="JSON (default benchmarks/results/pareto_<task>_reeval.json)")
    args = p.parse_args(argv)

    import design_engine  # noqa: F401  (x64, cache)
    from design_engine.design.design_io import load_design
    from design_engine.design.evaluator import TaskEvaluator
    from design_engine.solve.policy import contact_config

    try:
        sweep = json.loads((args.sweep / "sweep.json").read_text())
        front = json.loads((args.sweep / "front.json").read_text())
    except (OSError, ValueError) as exc:
        print(f"bench_front_reference: {exc}", file=sys.stderr)
        return 2
    if front.get("senses") != ["max", "min"]:
        print("bench_front_reference: the ratio J1/J2 needs a protection front (max, min)",
              file=sys.stderr)
        return 2
    points = sorted((q for q in front["front"] if q["J2"] > 0), key=lambda q: -q["J1"] / q["J2"])
    task = ramp_task(sweep["task"], tuple(sweep["size"]))
    evaluator = TaskEvaluator(task, config=contact_config())
    out = args.out or ROOT / f"benchmarks/results/pareto_{sweep['task']}_reeval.json"
    report = {"sweep": str(args.sweep), "model": "reference: dynamic ramp, Dopri8 rtol 1e-8 "
              "atol 1e-4 with contact (TaskEvaluator, configuration forced)", "points": []}
    a, b = front["terms"]
    for q in tqdm(points[:args.top], desc="reference model", unit="design"):
        _, x = load_design(args.sweep / q["design"])
        ev = evaluator.evaluate(x)
        j = task.objectives_si(ev.terms)
        report["points"].append({
            "run": q["run"], "eval": q["eval"], "design": q["design"],
            "default_model": {"J1": q["J1"], "J2": q["J2"], "ratio": q["J1"] / q["J2"]},
            "reference_model": {"J1": j[a], "J2": j[b], "ratio": j[a] / j[b]},
            "wall_s": ev.sim_s})
        out.write_text(json.dumps(report, indent=1))  # after every design: nothing lost
    for r in report["points"]:
        print(f"{r['run']} eval {r['eval']}: ratio {r['default_model']['ratio']:.0f} (default "
              f"model), {r['reference_model']['ratio']:.0f} (reference model)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
