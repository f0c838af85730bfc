"""Experiment against simulation on the simulated rig: accuracy and wall time (issue numbers).

Runs `metarig rig` (all nodes in one process, tracking and comparison after the capture) on a
24x16 focusing design at 1000 fps with camera noise on, then `metarig compare --poses truth` on
the same recording, which splits the error into its model part (truth against simulation) and
its tracking part (the rest). Writes `benchmarks/results/bench_compare.json`.

    python benchmarks/bench_compare.py --design runs/bench-design/focusing/design.json \
        [--m-per-px 4e-4 --width 1000 --height 700] [--out runs/bench-compare]
"""

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _run(argv: list[str]) -> float:
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "metarig", *argv], check=True, cwd=ROOT)
    return time.perf_counter() - t0


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--design", default=str(ROOT / "runs/bench-design/focusing/design.json"),
                   help="design file of the sample (default: the focusing benchmark's result)")
    p.add_argument("--m-per-px", type=float, default=4e-4)
    p.add_argument("--width", type=int, default=1000)
    p.add_argument("--height", type=int, default=700)
    p.add_argument("--out", type=Path, default=ROOT / "runs/bench-compare")
    p.add_argument("--results", type=Path, default=ROOT / "benchmarks/results/bench_compare.json")
    args = p.parse_args()
    run = args.out / "rig"
    load0 = os.getloadavg()
    wall_rig = _run(["rig", "--scene", "focusing-24x16", "--design", args.design, "--strain",
                     "0", "--width", str(args.width), "--height", str(args.height),
                     "--m-per-px", str(args.m_per_px), "--out", str(run)])
    _run(["compare", str(run), "--poses", "truth", "--out", str(args.out / "truth"), "-q"])
    tracked = json.loads((run / "summary.json").read_text())
    truth = json.loads((args.out / "truth" / "summary.json").read_text())
    rig = json.loads((run / "run.json").read_text())
    keys = ("velocity_nrmse", "energy_map_correlation", "target_peak_ke_rel_err",
            "max_displacement_error_m", "lost_units")
    result = {
        "design": args.design, "frames": tracked["frames"], "n_units": tracked["n_units"],
        "m_per_px": args.m_per_px, "frame_px": [args.width, args.height],
        "tracked_vs_simulated": {k: tracked[k] for k in keys},
        "truth_vs_simulated (model part)": {k: truth[k] for k in keys},
        "wall_s": {"metarig rig (total)": wall_rig,
                   "capture": rig["timings_s"].get("total_wall"),
                   "track and compare": rig["timings_s"].get("track_and_compare"),
                   "comparison simulation": tracked["timings_s"]["simulation"]},
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(),
                    "load_before": load0, "load_after": os.getloadavg()},
    }
    args.results.parent.mkdir(parents=True, exist_ok=True)
    args.results.write_text(json.dumps(result, indent=2))
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
