"""Pre-compressed experiments through the camera and DIC: the default `metarig rig` (2 %) and
runs at 5 % and 8 %, each compared with its simulation from the tracked poses and from the
simulated rig's ground truth, on a quiet machine and with busy-loop processes beside it.

Per run: velocity NRMSE, largest displacement error and lost units of the comparison through
DIC (what `metarig rig` reports) and through the truth poses (`metarig compare --poses truth`:
the model part, which must not depend on the machine's load), the gap between the two (the
tracking part), the tracked poses against the truth (RMS position and rotation error over all
unit-frames, and in the first, pre-compressed frame; the velocity NRMSE of the tracked rates
against the true ones, beside the tracking noise the comparison states), and the messages
recorded. The simulated
rig's truth and footage (/camera/ground_truth, /camera/image_raw, /camera/reference_image) are
fingerprinted (SHA-256 of their payloads) with the camera's line on the device records it
solved the specimen under: for one strain they must be the same at every load
(`same_at_every_load`).

Writes `<out>/bench_precompressed.json` (machine, load before and after each run) after every
run; a run whose folder already holds both comparisons is read back, not repeated (resume after
an interrupt). Prints a table.
"""

import argparse
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from check_identical import topic_fingerprints
from machine import describe

BIN = Path(sys.prefix) / "bin"



def _run(cmd: list[str], env: dict) -> str:
    r = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=1800)
    if r.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{r.stderr[-3000:]}")
    return r.stdout + r.stderr


def pose_errors(run: Path) -> dict:
    """Tracked poses (`tracks.npz`) against the recorded ground truth."""
    from metarig.polygon import area_centroids
    from ros_nodes.logic.recording import read_recording

    rec = read_recording(run / "recording.mcap")
    polygons = np.array(json.loads((run / "design.json").read_text())["polygons_m"])
    truth, _ = rec.poses("/camera/ground_truth", area_centroids(polygons))
    tracked = np.load(run / "tracks.npz")["q"]
    m_per_px = json.loads((run / "calibration.json").read_text())["m_per_px"]
    e = tracked - truth.q
    pos = np.hypot(e[..., 0], e[..., 1])
    # the tracking part of the velocity figure as the comparison computes it (rates after the
    # onset, over the simulated RMS speed), against the noise the comparison states for it
    from comparison.metrics import frame_rates

    summary = json.loads((run / "summary.json").read_text())
    t = np.load(run / "tracks.npz")["t"]
    keep = t >= summary["onset_s"] - 1e-9
    used = np.all(np.isfinite(tracked), axis=(0, 2))
    v_sim = frame_rates(t, np.load(run / "simulated.npz")["q"])[keep][:, used, :2]
    dv = (frame_rates(t, tracked) - frame_rates(t, truth.q))[keep][:, used, :2]
    v_rms = np.sqrt(np.mean(np.sum(v_sim**2, axis=-1)))
    return {"position_rms_px": float(np.sqrt(np.nanmean(pos**2)) / m_per_px),
            "rotation_rms_mrad": float(np.sqrt(np.nanmean(e[..., 2] ** 2)) * 1e3),
            "first_frame_position_max_px": float(np.nanmax(pos[0]) / m_per_px),
            "first_frame_rotation_max_mrad": float(np.nanmax(np.abs(e[0, :, 2])) * 1e3),
            "largest_true_rotation_rad": float(np.abs(truth.q[0, :, 2]).max()),
            "velocity_nrmse_tracked_vs_truth": float(np.sqrt(np.mean(np.sum(dv**2, axis=-1)))
                                                     / v_rms),
            "velocity_noise_nrmse_stated": summary.get("velocity_noise_nrmse"),
            "largest_true_displacement_px": float(
                np.hypot(truth.q[0, :, 0], truth.q[0, :, 1]).max() / m_per_px)}


SIMULATED = ("/camera/ground_truth", "/camera/image_raw", "/camera/reference_image")
NOISE_KEYS = ("velocity_noise_nrmse", "velocity_nrmse_beyond_noise")


def one(out: Path, strain: float, load: int, env: dict) -> dict:
    run = out / f"strain{strain:g}-load{load}"
    truth_dir = run / "truth"
    if not (run / "summary.json").exists() or not (truth_dir / "summary.json").exists():
        burners = [subprocess.Popen([sys.executable, "-c", "while True: pass"])
                   for _ in range(load)]
        load0 = os.getloadavg()
        t0 = time.monotonic()
        try:
            log = _run([str(BIN / "metarig"), "rig", "--strain", str(strain), "--out", str(run)],
                       env)
            (run / "rig.log").write_text(log)
            _run([str(BIN / "metarig"), "compare", str(run), "--poses", "truth", "--out",
                  str(truth_dir), "-q"], env)
        finally:
            for b in burners:
                b.kill()
        (run / "bench_load.json").write_text(json.dumps(
            {"load_before": load0, "load_after": os.getloadavg(),
             "wall_s": time.monotonic() - t0}))
    dic = json.loads((run / "summary.json").read_text())
    truth = json.loads((truth_dir / "summary.json").read_text())
    meta = json.loads((run / "run.json").read_text())
    keys = ("velocity_nrmse", "max_displacement_error_m", "lost_units",
            "energy_map_correlation", "target_peak_ke_rel_err")
    topics = topic_fingerprints(run)
    records = re.findall(r"device records up to .*", (run / "rig.log").read_text()) \
        if (run / "rig.log").exists() else []
    return {"strain": strain, "background_load_processes": load,
            **json.loads((run / "bench_load.json").read_text()),
            # the simulated rig's truth and footage: the same at every load (one seed)
            "fingerprints": {t: topics.get(t) for t in SIMULATED},
            "device_records": records[-1] if records else "",
            "messages_recorded": meta["recording"]["messages"],
            "frames": meta["frames"],
            "dic": {k: dic[k] for k in (*keys, *NOISE_KEYS) if k in dic},
            "truth": {k: truth[k] for k in keys},
            "tracking_part_pp": 100 * (dic["velocity_nrmse"] - truth["velocity_nrmse"]),
            # the tracking noise's part told apart (comparison.metrics): beyond it against truth
            "beyond_noise_gap_pp": 100 * (dic["velocity_nrmse_beyond_noise"]
                                          - truth["velocity_nrmse"])
            if "velocity_nrmse_beyond_noise" in dic else None,
            "displacement_gap_mm": 1e3 * (dic["max_displacement_error_m"]
                                          - truth["max_displacement_error_m"]),
            "poses": pose_errors(run)}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--out", type=Path, default=Path("runs/bench_precompressed"))
    p.add_argument("--strains", default="0.02,0.05,0.08")
    p.add_argument("--loads", default="0,2", help="busy-loop processes beside each pass")
    p.add_argument("--results", type=Path, default=None,
                   help="also copy the JSON here (e.g. benchmarks/results)")
    args = p.parse_args(argv)
    try:
        strains = [float(s) for s in args.strains.split(",")]
        loads = [int(s) for s in args.loads.split(",")]
    except ValueError:
        p.error("--strains and --loads take comma-separated numbers")
    args.out.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, ROS_DOMAIN_ID=str(150 + os.getpid() % 40),
               ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    res = {"machine": describe(), "command": "metarig rig --strain S --out DIR; metarig "
           "compare DIR --poses truth", "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
           "runs": []}
    for load in loads:
        for s in strains:
            print(f"strain {s:g}, {load} busy processes ...", flush=True)
            res["runs"].append(one(args.out, s, load, env))
            r = res["runs"][-1]
            print(f"  DIC {100 * r['dic']['velocity_nrmse']:.2f} %, truth "
                  f"{100 * r['truth']['velocity_nrmse']:.2f} %, lost {r['dic']['lost_units']}",
                  flush=True)
            for d in filter(None, (args.out, args.results)):
                d.mkdir(parents=True, exist_ok=True)
                (d / "bench_precompressed.json").write_text(json.dumps(res, indent=2))
    res["same_at_every_load"] = {
        f"{s:g}": len({json.dumps(r["fingerprints"], sort_keys=True) for r in res["runs"]
                       if r["strain"] == s}) == 1 for s in strains}
    for d in filter(None, (args.out, args.results)):
        (d / "bench_precompressed.json").write_text(json.dumps(res, indent=2))
    print(f"truth and footage the same at every load (per strain): {res['same_at_every_load']}")
    print(f"{'strain':>7}{'load':>6}{'NRMSE DIC':>11}{'beyond noise':>13}{'truth':>8}"
          f"{'gap pp':>8}{'max disp DIC':>14}"
          f"{'truth':>8}{'lost':>6}{'pos px':>8}{'rot mrad':>9}{'msgs':>6}")
    for r in res["runs"]:
        print(f"{r['strain']:>7.2f}{r['background_load_processes']:>6}"
              f"{100 * r['dic']['velocity_nrmse']:>10.2f}%"
              f"{100 * r['dic'].get('velocity_nrmse_beyond_noise', float('nan')):>12.2f}%"
              f"{100 * r['truth']['velocity_nrmse']:>7.2f}%"
              f"{r['tracking_part_pp']:>8.2f}{1e3 * r['dic']['max_displacement_error_m']:>11.3f} mm"
              f"{1e3 * r['truth']['max_displacement_error_m']:>8.3f}{r['dic']['lost_units']:>6}"
              f"{r['poses']['position_rms_px']:>8.3f}{r['poses']['rotation_rms_mrad']:>9.2f}"
              f"{r['messages_recorded']:>6}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
