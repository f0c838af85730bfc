"""Experiment sequencer node: owns simulated time and runs the procedure of `logic.sequence`.

Node name `sequencer`. Publishes `/clock` (simulated time, `clock_step_s` steps at
`real_time_factor`), `/rig/phase` and `/rig/config` (latched strings), `/rig/stop` (on abort).
Calls the stage, shaker, camera and recorder services; waits on their status topics with
deadlines. `Sequencer.run()` is called by `metarig rig` with the executor spinning elsewhere.
"""

import json
import logging
import threading
import time
from pathlib import Path

from rclpy.node import Node
from rosgraph_msgs.msg import Clock
from std_msgs.msg import Empty, String
from std_srvs.srv import Trigger

from metarig_msgs.srv import FirePulse, SetStrain
from ros_nodes import convert
from ros_nodes.logic.sequence import ExperimentPlan, Phase
from ros_nodes.nodes._common import CLOCK, COMMAND, LATCHED

log = logging.getLogger("metarig.rig")


class RigError(RuntimeError):
    """The experiment could not proceed (a refusal, a fault or a timeout); message says why."""


class SequencerNode(Node):
    """Clock owner and procedure runner (see module docstring)."""

    def __init__(self, plan: ExperimentPlan, config: dict, **kwargs):
        super().__init__("sequencer", **kwargs)
        self.plan = plan
        self._clock_pub = self.create_publisher(Clock, "/clock", CLOCK)
        self._phase_pub = self.create_publisher(String, "/rig/phase", LATCHED)
        self._config_pub = self.create_publisher(String, "/rig/config", LATCHED)
        self._stop_pub = self.create_publisher(Empty, "/rig/stop", COMMAND)
        self._config_pub.publish(String(data=json.dumps(config, default=str)))
        self.sim_ns = 0
        self._limit_ns = 2**62
        self._run_clock = threading.Event()
        self._quit = threading.Event()
        self._clock_thread = threading.Thread(target=self._clock_loop, daemon=True)
        self.latest: dict[str, object] = {}
        self.events: list[tuple[str, float]] = []
        for topic, key in (("/stage/state", "stage"), ("/camera/status", "camera"),
                           ("/recorder/status", "recorder"), ("/rig/design", "design")):
            qos = LATCHED if key in ("stage", "camera", "design") else COMMAND
            self.create_subscription(String, topic, self._keep(key), qos)
        self.clients_ = {
            "set_strain": self.create_client(SetStrain, "/stage/set_strain"),
            "stage_stop": self.create_client(Trigger, "/stage/stop"),
            "fire": self.create_client(FirePulse, "/shaker/fire"),
            "shaker_stop": self.create_client(Trigger, "/shaker/stop"),
            "cam_start": self.create_client(Trigger, "/camera/start"),
            "cam_stop": self.create_client(Trigger, "/camera/stop"),
            "rec_start": self.create_client(Trigger, "/recorder/start"),
            "rec_stop": self.create_client(Trigger, "/recorder/stop"),
        }
        self._publish_clock()
        self._clock_thread.start()

    # clock ------------------------------------------------------------------------------------
    def _publish_clock(self) -> None:
        self._clock_pub.publish(convert.clock(self.sim_ns))

    def _clock_loop(self) -> None:
        step_ns = int(round(self.plan.clock_step_s * 1e9))
        rtf = self.plan.real_time_factor
        while not self._quit.is_set():
            if not self._run_clock.wait(0.05):
                continue
            t0 = time.perf_counter()
            if self.sim_ns + step_ns > self._limit_ns:
                self._run_clock.clear()  # reached the requested time exactly: hold it
                continue
            self.sim_ns += step_ns
            self._publish_clock()
            if rtf > 0:
                rest = step_ns * 1e-9 / rtf - (time.perf_counter() - t0)
                if rest > 0:
                    time.sleep(rest)

    @property
    def sim_s(self) -> float:
        return self.sim_ns * 1e-9

    def close(self) -> None:
        self._quit.set()
        self._clock_thread.join(timeout=1.0)

    # waiting helpers --------------------------------------------------------------------------
    def _keep(self, key: str):
        def cb(msg: String) -> None:
            try:
                self.latest[key] = json.loads(msg.data)
            except ValueError:
                self.latest[key] = msg.data
        return cb

    def _until(self, predicate, what: str, timeout_s: float | None = None) -> None:
        deadline = time.monotonic() + (timeout_s or self.plan.timeout_s)
        while not predicate():
            if time.monotonic() > deadline:
                raise RigError(f"timed out waiting for {what}")
            time.sleep(0.005)

    def call(self, name: str, request, timeout_s: float = 30.0):
        client = self.clients_[name]
        self._until(client.service_is_ready, f"service {client.srv_name}", timeout_s)
        fut = client.call_async(request)
        self._until(fut.done, f"the answer of {client.srv_name}", timeout_s)
        return fut.result()

    def phase(self, p: Phase) -> None:
        self.events.append((p.value, self.sim_s))
        self._phase_pub.publish(String(data=p.value))
        log.info("phase %-11s t_sim = %.4f s", p.value, self.sim_s)

    def run_clock_until(self, t_s: float) -> None:
        """Run simulated time up to exactly t_s (rounded to the clock step), then hold it."""
        step = int(round(self.plan.clock_step_s * 1e9))
        self._limit_ns = int(round(t_s * 1e9 / step)) * step
        self._run_clock.set()
        self._until(lambda: self.sim_ns >= self._limit_ns, f"simulated time {t_s:.4f} s")
        self._run_clock.clear()

    def pause_clock(self) -> None:
        self._run_clock.clear()

    # the procedure ----------------------------------------------------------------------------
    def run(self) -> dict:
        """Run the experiment; returns timings. Raises RigError (devices are stopped by caller)."""
        p = self.plan
        w0 = time.monotonic()
        self.phase(Phase.STARTING)
        self._until(lambda: "design" in self.latest or
                    (self.latest.get("camera") or {}).get("state") == "error",
                    "the specimen to be built (/rig/design)")
        if (self.latest.get("camera") or {}).get("state") == "error":
            raise RigError(f"camera: {self.latest['camera'].get('message')}")
        for name in self.clients_:
            self._until(self.clients_[name].service_is_ready, f"service {name}", 60.0)
        timings = {"startup": time.monotonic() - w0}

        w = time.monotonic()
        self.phase(Phase.PRECOMPRESS)
        r = self.call("set_strain", SetStrain.Request(strain=p.strain))
        if not r.accepted:
            raise RigError(f"stage: {r.message}")
        self._limit_ns = 2**62
        self._run_clock.set()
        self._until(lambda: str(self.latest.get("stage", "")).startswith(("holding", "fault"))
                    or (p.strain == 0 and self.sim_s > 0.005), "the stages to reach the strain")
        if str(self.latest.get("stage")).startswith("fault"):
            raise RigError(f"stage {self.latest['stage']}")
        self.phase(Phase.SETTLE)
        self.run_clock_until(self.sim_s + p.settle_s)
        timings["precompress_settle"] = time.monotonic() - w

        w = time.monotonic()
        self.pause_clock()
        self.phase(Phase.RECORD)
        self.call("rec_start", Trigger.Request())
        # recording, and subscribed to every rig topic: a sample sent before the match is lost
        self._until(lambda: (self.latest.get("recorder") or {}).get("recording") and
                    (self.latest.get("recorder") or {}).get("matched", True),
                    "the recorder to start and match every topic", 30.0)
        t_rec = self.sim_s
        if not self.call("cam_start", Trigger.Request()).success:
            raise RigError("camera refused to start")
        r = self.call("fire", FirePulse.Request(waveform=p.waveform, amplitude_m=p.amplitude_m,
                                                frequency_hz=p.frequency_hz, cycles=p.cycles,
                                                delay_s=p.pre_trigger_s))
        if not r.accepted:
            raise RigError(f"shaker: {r.message}")
        self.phase(Phase.PULSE)
        self.run_clock_until(t_rec + p.record_s)
        self.pause_clock()
        timings["record_live"] = time.monotonic() - w

        w = time.monotonic()
        self.phase(Phase.DEVELOP)
        self.call("cam_stop", Trigger.Request())
        self._until(lambda: (self.latest.get("camera") or {}).get("state") in ("done", "error"),
                    "the camera footage")
        cam = self.latest["camera"]
        if cam["state"] == "error":
            raise RigError(f"camera: {cam['message']}")
        n = int(cam["frames"])
        try:
            self._until(lambda: (self.latest.get("recorder") or {}).get("counts", {})
                        .get("/camera/image_raw", 0) >= n, f"the recorder to write {n} frames", 30.0)
        except RigError as e:
            log.warning("%s; finishing with what arrived (the report counts the loss)", e)
        timings["develop_publish"] = time.monotonic() - w
        timings["frames"] = n
        return timings

    def stop_devices(self) -> None:
        """Bring the rig to rest: broadcast /rig/stop, then the stop services (best effort)."""
        self._stop_pub.publish(Empty())
        for name in ("shaker_stop", "stage_stop"):
            try:
                self.call(name, Trigger.Request(), timeout_s=5.0)
            except RigError as e:
                log.warning("%s", e)

    def stop_recorder(self, timeout_s: float = 30.0) -> dict | None:
        try:
            r = self.call("rec_stop", Trigger.Request(), timeout_s=timeout_s)
        except RigError as e:
            log.warning("%s", e)
            return None
        return json.loads(r.message) if r.success else None


def main(args=None) -> int:
    """The sequencer alone (`metarig-sequencer`): same as `metarig rig --processes`."""
    import sys

    from ros_nodes.cli_rig import rig_main

    return rig_main(["--processes", *(sys.argv[1:] if args is None else args)])


if __name__ == "__main__":
    raise SystemExit(main())
