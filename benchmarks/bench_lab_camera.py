"""Lab camera benchmark: frames/s sustained from pylon's emulated camera into the recorder, and
whether any frame is lost without being counted.

For each region of interest and requested frame rate: the camera node on a lab file
(`hardware: lab`, pylon's emulator, `PYLON_CAMEMU=1`) and the recorder node run as two
processes on an isolated domain; this script's driver node starts the stream (`/camera/start`),
lets it run `--seconds`, stops it (`/camera/stop`), waits until the recorder has written what
was published and ends the recording (`/recorder/stop`). The MCAP is then read back with the
`mcap` package. Every frame is accounted for:
- taken by the camera = `received` + `lost` of the camera node's status (its frame counter);
- `lost_at_camera`: counter jumps (taken, never delivered by the driver): counted, not silent;
- published by the node, recorded in the file; `published - recorded` is what `run.json`
  reports as `frames.lost` (the recorder's `dropped` is its known part): counted, not silent;
- silent loss = frames received but never published (`received - published`), plus any
  difference between the file's count and the recorder's own report: nothing counts those.
Sustained rate = recorded frames / the span of their stamps. For comparison, the emulator
alone: the frames/s the camera driver grabs from it in this process, no ROS (`--alone-s`), at
each region of interest as fast as it goes. Writes
`<out>/bench_lab_camera.json` (machine, load average before and after) and prints a table.
"""

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from machine import describe

BIN = Path(sys.prefix) / "bin"
IMAGE = "/camera/image_raw"
LAB = """[camera]
driver = "pylon"
serial = "0815-0000"
frame_rate_hz = {rate}
exposure_s = 0.0001
roi = [0, 0, {w}, {h}]
max_frame_rate_hz = 5000.0
exposure_range_s = [1e-6, 0.01]
buffers = 256
"""


class Driver:
    """The benchmark's own node: starts and stops the camera, reads the statuses."""

    def __init__(self, domain: int):
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import DurabilityPolicy, QoSProfile
        from std_msgs.msg import String
        from std_srvs.srv import Trigger

        os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")  # as the nodes
        self.ctx = Context()
        rclpy.init(context=self.ctx, domain_id=domain)
        self.node = rclpy.create_node("bench_driver", context=self.ctx)
        self.ex = SingleThreadedExecutor(context=self.ctx)
        self.ex.add_node(self.node)
        self.camera, self.recorder = {}, {}
        latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.node.create_subscription(String, "/camera/status",
                                      lambda m: self.camera.update(json.loads(m.data)), latched)
        self.node.create_subscription(String, "/recorder/status",
                                      lambda m: self.recorder.update(json.loads(m.data)), 10)
        self.trigger = Trigger
        self.clients = {n: self.node.create_client(Trigger, n) for n in
                        ("/camera/start", "/camera/stop", "/recorder/start", "/recorder/stop")}

    def until(self, predicate, what: str, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        while not predicate():
            if time.monotonic() > deadline:
                raise RuntimeError(f"timed out waiting for {what}")
            self.ex.spin_once(timeout_sec=0.05)

    def call(self, name: str, timeout_s: float = 60.0):
        client = self.clients[name]
        self.until(client.service_is_ready, name, timeout_s)
        fut = client.call_async(self.trigger.Request())
        self.until(fut.done, f"the answer of {name}", timeout_s)
        return fut.result()

    def close(self) -> None:
        import rclpy

        self.ex.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.ctx)


def run_one(work: Path, w: int, h: int, rate: float, seconds: float, domain: int) -> dict:
    lab, mcap = work / f"lab_{w}x{h}_{rate:g}.toml", work / f"cam_{w}x{h}_{rate:g}.mcap"
    lab.write_text(LAB.format(rate=rate, w=w, h=h))
    mcap.unlink(missing_ok=True)
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               PYLON_CAMEMU="1", PYTHONUNBUFFERED="1")
    rec = subprocess.Popen([str(BIN / "metarig-recorder"), "--ros-args", "-p", f"path:={mcap}",
                            "-p", f"topics:=[{IMAGE}, /camera/camera_info]", "-p",
                            "queue_depth:=5000", "-p", "chunk_size:=4194304"],
                           env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    cam = subprocess.Popen([str(BIN / "metarig-camera"), "--ros-args", "-p", "hardware:=lab",
                            "-p", f"lab_file:={lab}"],
                           env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    drv = Driver(domain)
    try:
        drv.until(lambda: drv.camera.get("state") == "idle", "the lab camera to open", 60.0)
        drv.call("/recorder/start")
        drv.until(lambda: drv.recorder.get("recording") and drv.recorder.get("matched")
                  and drv.node.count_subscribers(IMAGE) >= 1, "the recorder to subscribe", 60.0)
        t0 = time.monotonic()
        r = drv.call("/camera/start")
        if not r.success:
            raise RuntimeError(f"the camera refused: {r.message}")
        while time.monotonic() - t0 < seconds:
            drv.ex.spin_once(timeout_sec=0.1)
        drv.call("/camera/stop")
        drv.until(lambda: drv.camera.get("state") in ("done", "error"), "the camera to stop", 30.0)
        cam_status = dict(drv.camera)
        published = int(cam_status["frames"])
        # the recorder writes what was published, or stops gaining for 2 s
        last, since = -1, time.monotonic()
        while drv.recorder.get("counts", {}).get(IMAGE, 0) < published and \
                time.monotonic() - since < 2.0:
            drv.ex.spin_once(timeout_sec=0.1)
            n = drv.recorder.get("counts", {}).get(IMAGE, 0)
            if n != last:
                last, since = n, time.monotonic()
        report = json.loads(drv.call("/recorder/stop").message)
    finally:
        drv.close()
        for proc in (cam, rec):
            proc.send_signal(signal.SIGINT)
        for proc in (cam, rec):
            try:
                proc.communicate(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
    from mcap.reader import make_reader

    stamps = []
    with mcap.open("rb") as f:
        for _, _, message in make_reader(f).iter_messages(topics=[IMAGE]):
            stamps.append(message.log_time)
    stamps = np.array(stamps)
    recorded = int(stamps.size)
    t = report["topics"].get(IMAGE, {"count": 0, "dropped": 0, "missing_by_stamp": 0})
    received, lost = int(cam_status.get("received", 0)), int(cam_status.get("lost", 0))
    span = (stamps[-1] - stamps[0]) * 1e-9 if recorded > 1 else float("nan")
    silent = (received - published) + abs(recorded - int(t["count"]))
    out = {"roi_px": [w, h], "requested_rate_hz": rate,
           "device_rate_hz": cam_status.get("settings", {}).get("frame_rate_hz"),
           "seconds": seconds, "taken": received + lost, "lost_at_camera": lost,
           "received": received, "published": published, "recorded": recorded,
           "recorder_count": int(t["count"]), "recorder_dropped": int(t["dropped"]),
           "missing_from_file": published - recorded, "silent_loss": silent,
           "sustained_frames_per_s": (recorded - 1) / span if recorded > 1 else 0.0,
           "megabytes_per_s": (recorded - 1) * w * h / span / 1e6 if recorded > 1 else 0.0,
           "stamp_gaps": int(t.get("gaps", 0)), "camera_state": cam_status.get("state"),
           "mcap_bytes": mcap.stat().st_size}
    mcap.unlink(missing_ok=True)
    return out


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


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--out", type=Path, default=Path("benchmarks/results"))
    p.add_argument("--seconds", type=float, default=10.0, help="stream length per case")
    p.add_argument("--rates", type=float, nargs="+", default=[50.0, 100.0, 1000.0],
                   help="requested frame rates, Hz")
    p.add_argument("--rois", nargs="+", default=["640x480", "1024x1040"],
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
                c = run_one(Path(tmp), w, h, rate, args.seconds, domain)
                cases.append(c)
                print(f"{w}x{h} at {rate:g} Hz: {c['recorded']}/{c['taken']} frames, "
                      f"{c['sustained_frames_per_s']:.1f} frames/s, lost at camera "
                      f"{c['lost_at_camera']}, missing {c['missing_from_file']}, silent "
                      f"{c['silent_loss']}", flush=True)
    res = {"machine": describe(),
           "load_average_1_5_15_min": {"before": load0, "after": os.getloadavg()},
           "wall_s": time.monotonic() - t0, "camera": "pylon emulator (PYLON_CAMEMU=1), mono8, "
           "camera node and recorder node in two processes",
           "emulator_alone_frames_per_s": alone, "cases": cases}
    path = args.out / "bench_lab_camera.json"
    path.write_text(json.dumps(res, indent=2))
    print(f"{'roi':<11}{'asked Hz':>9}{'frames/s':>10}{'alone':>7}{'MB/s':>7}{'taken':>7}"
          f"{'recorded':>9}{'lost@cam':>9}{'missing':>8}{'silent':>7}")
    for c in cases:
        roi = "x".join(map(str, c["roi_px"]))
        print(f"{roi:<11}{c['requested_rate_hz']:>9g}{c['sustained_frames_per_s']:>10.1f}"
              f"{alone.get(roi, float('nan')):>7.1f}{c['megabytes_per_s']:>7.1f}{c['taken']:>7}"
              f"{c['recorded']:>9}{c['lost_at_camera']:>9}{c['missing_from_file']:>8}"
              f"{c['silent_loss']:>7}")
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
