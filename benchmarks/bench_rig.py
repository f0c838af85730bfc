"""Rig benchmarks: camera source + recorder throughput, and a full simulated experiment.

1. Throughput: the camera node (test-pattern source, 640x480 mono8, paced at `--fps`) and the
   recorder node run as two processes on an isolated domain; the recorder writes the MCAP.
   Afterwards the recording is read back and every frame checked: delivered rate, transport
   drops (DDS sequence numbers), frames missing by stamp, and latency (receive time - capture
   stamp) percentiles. Repeated `--runs` times; the median run by delivered rate is reported.
2. Full experiment: `metarig rig` with its defaults (24x16 sample, 2 % pre-compression, the
   paper's pulse, 0.1 s of 1000 fps 640x480 footage), wall time by phase.

Writes `<out>/bench_rig.json` (with the CPU and the load average before and after, since other
work on a 2-core machine changes the throughput several-fold) and prints a table.
"""

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from machine import describe

BIN = Path(sys.prefix) / "bin"


def _env(domain: int) -> dict:
    env = dict(os.environ)
    env.update(ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               PYTHONUNBUFFERED="1")
    return env


def throughput(out: Path, fps: float, n: int, domain: int) -> dict:
    path = out / "throughput.mcap"
    if path.exists():
        path.unlink()
    env = _env(domain)
    rec = subprocess.Popen([str(BIN / "metarig-recorder"), "--ros-args", "-p", f"path:={path}",
                            "-p", "autostart:=true", "-p", "topics:=[/camera/image_raw]",
                            "-p", "queue_depth:=5000", "-p", "chunk_size:=4194304"],
                           env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    cam = subprocess.Popen([str(BIN / "metarig-camera"), "--ros-args", "-p", "source:=pattern",
                            "-p", f"fps:={fps}", "-p", f"n_frames:={n}", "-p", "rate_factor:=1.0"],
                           env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    # start the stream through the camera's service once both are up (helper node)
    code = f"""
import json, time, rclpy
from std_srvs.srv import Trigger
from std_msgs.msg import String
rclpy.init()
node = rclpy.create_node("bench_driver")
cli = node.create_client(Trigger, "/camera/start")
deadline = time.monotonic() + 60
while not cli.service_is_ready() or node.count_subscribers("/camera/image_raw") < 1:
    rclpy.spin_once(node, timeout_sec=0.1)
    assert time.monotonic() < deadline, "camera/recorder did not come up"
state = {{}}
node.create_subscription(String, "/camera/status", lambda m: state.update(json.loads(m.data)),
                         rclpy.qos.QoSProfile(depth=1, durability=rclpy.qos.DurabilityPolicy.TRANSIENT_LOCAL))
counts = {{}}
node.create_subscription(String, "/recorder/status",
                         lambda m: counts.update(json.loads(m.data).get("counts", {{}})), 10)
t0 = time.monotonic()
f = cli.call_async(Trigger.Request())
while state.get("state") != "done":
    rclpy.spin_once(node, timeout_sec=0.1)
    assert time.monotonic() < deadline + 120, "stream did not finish"
wall = time.monotonic() - t0
# let the recorder drain: until every frame is written or the count stops growing for 2 s
last, since = -1, time.monotonic()
while counts.get("/camera/image_raw", 0) < {n} and time.monotonic() - since < 2.0:
    rclpy.spin_once(node, timeout_sec=0.1)
    if counts.get("/camera/image_raw", 0) != last:
        last, since = counts.get("/camera/image_raw", 0), time.monotonic()
print(json.dumps({{"publish_wall_s": wall}}))
"""
    drv = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         timeout=400)
    cam.send_signal(2)
    rec.send_signal(2)
    rec.communicate(timeout=60)
    cam.communicate(timeout=60)
    if drv.returncode != 0:
        raise RuntimeError(drv.stderr[-2000:])
    pub_wall = json.loads(drv.stdout.strip().splitlines()[-1])["publish_wall_s"]
    from mcap.reader import make_reader

    stamps, recv, ids = [], [], []
    with open(path, "rb") as f:
        r = make_reader(f)
        report = json.loads({m.name: m.metadata for m in r.iter_metadata()}
                            ["recording_report"]["json"])
    with open(path, "rb") as f:
        for _, _, msg in make_reader(f).iter_messages():
            stamps.append(msg.log_time)
            recv.append(msg.publish_time)
            ids.append(int.from_bytes(msg.data[-640 * 480:][:2], "little"))
    stamps, recv = np.array(stamps), np.array(recv)
    lat = (recv - stamps) * 1e-6
    t = report["topics"]["/camera/image_raw"]
    span = (stamps.max() - stamps.min()) * 1e-9 if len(stamps) > 1 else float("nan")
    return {"fps_requested": fps, "frames_sent": n, "frames_recorded": int(len(stamps)),
            "frames_missing": int(n - len(set(ids))),
            "dropped_transport": t["missing_by_sequence"], "missing_by_stamp": t["missing_by_stamp"],
            "delivered_rate_hz": len(stamps) / pub_wall if pub_wall else float("nan"),
            "stamp_rate_hz": (len(stamps) - 1) / span if span else float("nan"),
            "latency_ms": {"p50": float(np.percentile(lat, 50)), "p95": float(np.percentile(lat, 95)),
                           "p99": float(np.percentile(lat, 99)), "max": float(lat.max())},
            "mcap_bytes": path.stat().st_size}


def experiment(out: Path, domain: int) -> dict:
    run = out / "experiment"
    t0 = time.monotonic()
    r = subprocess.run([str(BIN / "metarig"), "rig", "--out", str(run)], env=_env(domain),
                       capture_output=True, text=True, timeout=900)
    wall = time.monotonic() - t0
    if r.returncode != 0:
        raise RuntimeError(r.stderr[-3000:])
    s = json.loads((run / "run.json").read_text())
    return {"wall_s": wall, "timings_s": s["timings_s"], "messages": s["recording"]["messages"],
            "dropped": s["recording"]["dropped"],
            "frames": s["recording"]["topics"]["/camera/image_raw"]["count"],
            "mcap_bytes": (run / "recording.mcap").stat().st_size}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--out", type=Path, default=Path("runs/bench_rig"))
    p.add_argument("--fps", type=float, default=1000.0)
    p.add_argument("--frames", type=int, default=3000)
    p.add_argument("--runs", type=int, default=5,
                   help="throughput runs; the median by delivered rate is reported")
    p.add_argument("--background-load", type=int, default=0, metavar="N",
                   help="busy-loop processes competing for the cores during the throughput "
                        "runs (what happens when the machine is shared)")
    p.add_argument("--skip-experiment", action="store_true")
    args = p.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    domain = 150 + os.getpid() % 40
    load0 = os.getloadavg()
    burners = [subprocess.Popen([sys.executable, "-c", "while True: pass"])
               for _ in range(args.background_load)]
    runs = []
    try:
        for k in range(args.runs):
            runs.append(throughput(args.out, args.fps, args.frames, domain))
            print(f"run {k + 1}/{args.runs}: {runs[-1]['frames_recorded']}/{args.frames} "
                  f"frames, {runs[-1]['delivered_rate_hz']:.1f} frames/s", flush=True)
    finally:
        for b in burners:
            b.kill()
    median = sorted(runs, key=lambda r: r["delivered_rate_hz"])[len(runs) // 2]
    res = {"machine": describe(),
           "load_average_1_5_15_min": {"before": load0, "after_throughput": os.getloadavg()},
           "background_load_processes": args.background_load,
           "throughput": {**median, "note": f"median of {len(runs)} runs by delivered rate"},
           "throughput_runs": [{k: r[k] for k in ("frames_recorded", "dropped_transport",
                                                  "delivered_rate_hz")}
                               | {"latency_p50_ms": r["latency_ms"]["p50"],
                                  "latency_p99_ms": r["latency_ms"]["p99"]} for r in runs]}
    if not args.skip_experiment:
        res["experiment"] = experiment(args.out, domain + 1)
    (args.out / "bench_rig.json").write_text(json.dumps(res, indent=2))
    t = res["throughput"]
    print(f"{'camera+recorder 640x480 mono8':<34}{'value':>12}")
    print(f"{'requested fps':<34}{t['fps_requested']:>12.0f}")
    print(f"{'frames sent / recorded':<34}{t['frames_sent']:>6}/{t['frames_recorded']:<5}")
    print(f"{'frames missing from the file':<34}{t['frames_missing']:>12}")
    print(f"{'transport drops (seq)':<34}{t['dropped_transport']:>12}")
    print(f"{'missing by stamp':<34}{t['missing_by_stamp']:>12}")
    print(f"{'delivered rate, frames/s':<34}{t['delivered_rate_hz']:>12.1f}")
    for k in ("p50", "p95", "p99", "max"):
        print(f"{'latency ' + k + ', ms':<34}{t['latency_ms'][k]:>12.2f}")
    if "experiment" in res:
        e = res["experiment"]
        print(f"{'full experiment wall, s':<34}{e['wall_s']:>12.1f}")
        print(f"{'  frames / messages / dropped':<34}{e['frames']:>5}/{e['messages']}/{e['dropped']}")
        for k, v in e["timings_s"].items():
            print(f"{'  ' + k:<34}{v:>12.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
