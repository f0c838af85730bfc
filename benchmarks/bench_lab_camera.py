"""Lab camera benchmark: frames/s sustained from pylon's emulated camera into the recorder by
`metarig rig --hardware lab`, and whether any frame is lost without being counted.

For each region of interest and requested frame rate, and each way of running the nodes (all
in one process, or `--processes`): `metarig rig --hardware lab` on a lab file whose camera is
pylon's emulator (`PYLON_CAMEMU=1`) and whose shaker and stages are the simulators, on the
system clock, capturing `--seconds`. The run's MCAP is read back with the `mcap` package and
every frame accounted for from `run.json` `frames`:
- taken by the camera = `received_at_camera` + `lost_at_camera` (its frame counter);
- `lost_at_camera` (counter jumps) and `lost` (published, not in the file): counted;
- silent loss = frames received but never published (`received_at_camera - published`),
  plus any difference between the file's frames and the recorder's own count.
Sustained rate = recorded frames / the span of their stamps. For comparison, the emulator
alone: the frames/s the camera driver grabs from it in this process, no ROS (`--alone-s`),
asked for 1 kHz. Writes `<out>/bench_lab_camera.json` (machine, load average before and after)
and prints a table.
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from machine import describe

BIN = Path(sys.prefix) / "bin"
IMAGE = "/camera/image_raw"
LAB = """[shaker]
driver = "sim"
[stage]
driver = "sim"
[camera]
driver = "pylon"
serial = "0815-0000"
frame_rate_hz = {rate}
exposure_s = 0.0001
roi = [0, 0, {w}, {h}]
max_frame_rate_hz = 5000.0
exposure_range_s = [1e-6, 0.01]
buffers = 256
"""


def device_alone(w: int, h: int, seconds: float) -> float:
    """Frames/s grabbed from the emulator through the driver alone (no ROS), asked for 1 kHz."""
    from devices.camera.port import CameraLimits, CameraSettings
    from devices.camera.pylon import PylonCamera

    cam = PylonCamera(serial="0815-0000", buffers=256,
                      limits=CameraLimits(max_frame_rate_hz=5000.0, exposure_range_s=(1e-6, 0.01)))
    cam.open()
    try:
        cam.configure(CameraSettings(frame_rate_hz=1000.0, exposure_s=1e-4, roi=(0, 0, w, h)))
        cam.start()
        n, t0 = 0, time.monotonic()
        while time.monotonic() - t0 < seconds:
            n += cam.grab(1.0) is not None
        rate = n / (time.monotonic() - t0)
        cam.stop()
    finally:
        cam.close()
    return rate


def run_one(work: Path, w: int, h: int, rate: float, seconds: float, processes: bool,
            domain: int) -> dict:
    name = f"{w}x{h}_{rate:g}_{'processes' if processes else 'inprocess'}"
    lab, out = work / f"{name}.toml", work / name
    lab.write_text(LAB.format(rate=rate, w=w, h=h))
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               PYLON_CAMEMU="1")
    t0 = time.monotonic()
    r = subprocess.run([str(BIN / "metarig"), "rig", "--hardware", "lab", "--lab", str(lab),
                        "--out", str(out), "--nx", "6", "--ny", "5", "--strain", "0.01",
                        "--record-s", f"{seconds:g}", *(["--processes"] if processes else [])],
                       env=env, capture_output=True, text=True, timeout=600)
    wall = time.monotonic() - t0
    if r.returncode != 0:
        raise RuntimeError(f"{name}: metarig rig failed:\n{r.stderr[-3000:]}")
    run = json.loads((out / "run.json").read_text())
    from mcap.reader import make_reader

    stamps = []
    with (out / "recording.mcap").open("rb") as f:
        for _, _, message in make_reader(f).iter_messages(topics=[IMAGE]):
            stamps.append(message.log_time)
    stamps = np.array(stamps)
    recorded = int(stamps.size)
    frames, report = run["frames"], run["recording"]["topics"][IMAGE]
    received, lost = frames["received_at_camera"], frames["lost_at_camera"]
    span = (stamps[-1] - stamps[0]) * 1e-9 if recorded > 1 else float("nan")
    return {"roi_px": [w, h], "requested_rate_hz": rate,
            "nodes": "one process per node" if processes else "one process",
            "seconds": seconds, "taken": received + lost, "lost_at_camera": lost,
            "received": received, "published": frames["published"], "recorded": recorded,
            "recorder_count": int(report["count"]), "recorder_dropped": int(report["dropped"]),
            "missing_from_file": frames["lost"],
            "silent_loss": (received - frames["published"]) + abs(recorded - report["count"]),
            "sustained_frames_per_s": (recorded - 1) / span if recorded > 1 else 0.0,
            "megabytes_per_s": (recorded - 1) * w * h / span / 1e6 if recorded > 1 else 0.0,
            "stamp_gaps": int(report.get("gaps", 0)), "messages": run["recording"]["messages"],
            "dropped_all_topics": run["recording"]["dropped"], "run_wall_s": wall,
            "mcap_bytes": (out / "recording.mcap").stat().st_size}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--out", type=Path, default=Path("benchmarks/results"))
    p.add_argument("--seconds", type=float, default=10.0, help="capture length per case")
    p.add_argument("--rates", type=float, nargs="+", default=[1000.0],
                   help="requested frame rates, Hz (1000: as fast as the emulator goes)")
    p.add_argument("--rois", nargs="+", default=["640x480", "1024x1040", "2048x2048"],
                   help="regions of interest WxH (from the sensor's corner)")
    p.add_argument("--alone-s", type=float, default=5.0,
                   help="seconds of grabbing from the emulator without ROS per region (0: skip)")
    args = p.parse_args(argv)
    os.environ.setdefault("PYLON_CAMEMU", "1")  # before pylon's transport layer first looks
    args.out.mkdir(parents=True, exist_ok=True)
    domain = 150 + os.getpid() % 40
    load0, t0 = os.getloadavg(), time.monotonic()
    cases, alone = [], {}
    with tempfile.TemporaryDirectory() as tmp:
        for roi in args.rois:
            w, h = (int(v) for v in roi.split("x"))
            if args.alone_s > 0:
                alone[roi] = device_alone(w, h, args.alone_s)
                print(f"{roi}: the emulator alone gives {alone[roi]:.1f} frames/s", flush=True)
            for rate in args.rates:
                for processes in (False, True):
                    c = run_one(Path(tmp), w, h, rate, args.seconds, processes, domain)
                    cases.append(c)
                    print(f"{roi} at {rate:g} Hz, {c['nodes']}: {c['recorded']}/{c['taken']} "
                          f"frames, {c['sustained_frames_per_s']:.1f} frames/s, silent "
                          f"{c['silent_loss']}", flush=True)
    res = {"machine": describe(),
           "load_average_1_5_15_min": {"before": load0, "after": os.getloadavg()},
           "wall_s": time.monotonic() - t0,
           "camera": "pylon emulator (PYLON_CAMEMU=1), mono8, exposure 0.1 ms, through "
                     "`metarig rig --hardware lab` (simulated shaker and stages)",
           "emulator_alone_frames_per_s": alone, "cases": cases}
    path = args.out / "bench_lab_camera.json"
    path.write_text(json.dumps(res, indent=2))
    # the table: (heading, width (negative: left-aligned), value of a case)
    columns = [("roi", -11, lambda c: "x".join(map(str, c["roi_px"]))),
               ("nodes", -22, lambda c: c["nodes"]),
               ("frames/s", 10, lambda c: f"{c['sustained_frames_per_s']:.1f}"),
               ("alone", 7, lambda c: f"{alone.get('x'.join(map(str, c['roi_px'])), np.nan):.1f}"),
               ("MB/s", 7, lambda c: f"{c['megabytes_per_s']:.1f}")]
    columns += [(head, 9, lambda c, k=key: str(c[k])) for head, key in (
        ("taken", "taken"), ("recorded", "recorded"), ("lost@cam", "lost_at_camera"),
        ("missing", "missing_from_file"), ("silent", "silent_loss"))]
    for row in [None, *cases]:
        print("".join(f"{head if row is None else value(row):{'<' if w < 0 else '>'}{abs(w)}}"
                      for head, w, value in columns))
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
