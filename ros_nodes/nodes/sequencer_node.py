"""Experiment sequencer node: owns the rig's time; the rclpy port of `logic.experiment`.

Node name `sequencer`. On the simulated rig it publishes `/clock` (simulated time,
`clock_step_s` steps at `real_time_factor`); on lab devices (`simulated_clock=False`) the rig
runs on the system clock, which nobody can hold: the sequencer only waits for it, publishes no
`/clock`, and publishes the sample's nominal design on `/rig/design` itself (no simulated
camera builds it). Also `/rig/phase` and `/rig/config` (latched strings), `/rig/stop` (on
abort). Calls the stage, shaker, camera and recorder services; keeps their last status. The
procedure itself is `ros_nodes.logic.experiment.Experiment`, which `metarig rig` runs against
this node (`RigPort`) with the executor spinning elsewhere.
"""

import json
import logging
import threading
import time

from diagnostic_msgs.msg import DiagnosticArray
from lifecycle_msgs.srv import GetState
from metarig_msgs.srv import FirePulse, SetStrain
from rcl_interfaces.srv import SetParameters
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.parameter import Parameter
from rosgraph_msgs.msg import Clock
from std_msgs.msg import Empty, String
from std_srvs.srv import Trigger

from ros_nodes import convert
from ros_nodes import topics as T
from ros_nodes.logic.experiment import RigError
from ros_nodes.logic.sequence import ExperimentPlan, Phase
from ros_nodes.nodes._common import qos_profile

log = logging.getLogger("metarig.rig")
NAME = "sequencer"
__all__ = ["NAME", "RigError", "SequencerNode"]

# client name -> (service, type); the procedure waits for all of them before it starts
_SERVICES = {"set_strain": (T.STAGE_SET_STRAIN, SetStrain), "stage_stop": (T.STAGE_STOP, Trigger),
             "fire": (T.SHAKER_FIRE, FirePulse), "shaker_stop": (T.SHAKER_STOP, Trigger),
             "compensate": (T.SHAKER_COMPENSATE, FirePulse),
             "cam_start": (T.CAMERA_START, Trigger), "cam_stop": (T.CAMERA_STOP, Trigger),
             "cam_snapshot": (T.CAMERA_SNAPSHOT, Trigger),
             "rec_start": (T.RECORDER_START, Trigger), "rec_stop": (T.RECORDER_STOP, Trigger)}
# status topic -> key of `latest`
_WATCHED = {T.STAGE_STATE: "stage", T.CAMERA_STATUS: "camera", T.RECORDER_STATUS: "recorder",
            T.RIG_DESIGN: "design"}
# lifecycle nodes that must be active before anything moves
_LIFECYCLE = ("shaker", "stage")


def until(predicate, what: str, timeout_s: float) -> None:
    """Wait (the executor spins elsewhere) until `predicate()`; `RigError` after `timeout_s`."""
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise RigError(f"timed out waiting for {what}")
        time.sleep(0.005)


def ask(client, request, timeout_s: float, resend_s: float = 5.0, wait=until):
    """The answer of a query that may be repeated (a lifecycle node's state), sent again when
    none came within `resend_s`; `RigError` after `timeout_s`. `service_is_ready()` says only
    that this side has matched the server: a server that has just started may not yet have
    matched this client's response reader, and Fast DDS then drops the response ("failed to
    send response (timeout)" in the server's log), so one unanswered request says nothing.
    `wait(predicate, what, timeout_s)` waits as `until` does (the executor spinning elsewhere)
    or spins an executor itself, raising `RigError` when the time is up."""
    wait(client.service_is_ready, f"service {client.srv_name}", timeout_s)
    deadline = time.monotonic() + timeout_s
    while True:
        fut = client.call_async(request)
        try:
            wait(fut.done, f"the answer of {client.srv_name}",
                 min(resend_s, max(deadline - time.monotonic(), 0.0)))
            return fut.result()
        except RigError:
            client.remove_pending_request(fut)
            if time.monotonic() >= deadline:
                raise RigError(f"timed out waiting for the answer of {client.srv_name} "
                               f"(asked every {resend_s:g} s for {timeout_s:g} s)") from None


class SequencerNode(Node):
    """Clock owner and `RigPort` over ROS (see module docstring)."""

    def __init__(self, plan: ExperimentPlan, config: dict, simulated_clock: bool = True,
                 design_json: str | None = None, **kwargs):
        super().__init__(NAME, **kwargs)
        self.plan = plan
        self.simulated_clock = simulated_clock
        self._clock_pub = self.create_publisher(Clock, T.CLOCK.name, qos_profile(T.CLOCK.qos)) \
            if simulated_clock else None
        self._phase_pub = self.create_publisher(String, T.RIG_PHASE.name,
                                                qos_profile(T.RIG_PHASE.qos))
        self._config_pub = self.create_publisher(String, T.RIG_CONFIG.name,
                                                 qos_profile(T.RIG_CONFIG.qos))
        self._stop_pub = self.create_publisher(Empty, T.RIG_STOP.name, qos_profile(T.RIG_STOP.qos))
        self._config_pub.publish(String(data=json.dumps(config, default=str)))
        if design_json is not None:
            self._design_pub = self.create_publisher(String, T.RIG_DESIGN.name,
                                                     qos_profile(T.RIG_DESIGN.qos))
            self._design_pub.publish(String(data=design_json))
        self.sim_ns = 0
        self._published_ns = -1  # the last time published on /clock
        self._limit_ns = 2**62
        self._run_clock = threading.Event()
        self._quit = threading.Event()
        self._clock_thread = threading.Thread(target=self._clock_loop, daemon=True)
        self.latest: dict[str, object] = {}
        for topic, key in _WATCHED.items():
            self.create_subscription(String, topic.name, self._keep(key), qos_profile(topic.qos))
        services = dict(_SERVICES)
        if T.DIC_RESET.server in config.get("node_parameters", {}):  # a live tracker is
            services["dic_reset"] = (T.DIC_RESET, Trigger)  # ready once it offers this
        self.clients_ = {name: self.create_client(srv_type, srv.name)
                         for name, (srv, srv_type) in services.items()}
        self._hold_ns: int | None = None  # stamp of the stage's `holding` diagnostics
        self._shaker_fault = ""  # the shaker's `fault: ...` diagnostics
        self._compensation: tuple[bool, str] | None = None  # its compensation outcome
        self.create_subscription(DiagnosticArray, T.DIAGNOSTICS.name, self._on_diagnostics,
                                 qos_profile(T.DIAGNOSTICS.qos))
        # the camera's own parameter service: the capture starts at the time held here
        self._cam_params = self.create_client(SetParameters, "/camera/set_parameters")
        self._lifecycle = {name: self.create_client(GetState, f"/{name}/get_state")
                           for name in _LIFECYCLE}
        if simulated_clock:
            self._publish_clock()
            self._clock_thread.start()

    # clock ------------------------------------------------------------------------------------
    def _publish_clock(self) -> None:
        ns = self.sim_ns
        self._clock_pub.publish(convert.clock(ns))
        self._published_ns = ns

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
        return self.sim_ns * 1e-9 if self.simulated_clock else \
            self.get_clock().now().nanoseconds * 1e-9

    def close(self) -> None:
        self._quit.set()
        if self._clock_thread.is_alive():
            self._clock_thread.join(timeout=1.0)

    # waiting helpers --------------------------------------------------------------------------
    def _keep(self, key: str):
        def cb(msg: String) -> None:
            try:
                self.latest[key] = json.loads(msg.data)
            except ValueError:
                self.latest[key] = msg.data
        return cb

    def call(self, name: str, request, timeout_s: float = 30.0):
        """Call service `name` and wait for the answer; `RigError` after `timeout_s`."""
        client = self.clients_[name]
        until(client.service_is_ready, f"service {client.srv_name}", timeout_s)
        fut = client.call_async(request)
        until(fut.done, f"the answer of {client.srv_name}", timeout_s)
        return fut.result()

    # RigPort ----------------------------------------------------------------------------------
    def now(self) -> float:
        return time.monotonic()

    def sleep(self, dt_s: float) -> None:
        time.sleep(dt_s)

    def sim_time(self) -> float:
        return self.sim_s

    def announce(self, p: Phase) -> None:
        self._phase_pub.publish(String(data=p.value))

    def start_clock(self, until_s: float | None) -> None:
        if not self.simulated_clock:  # the system clock runs anyway: only the limit to wait for
            self._limit_ns = 2**62 if until_s is None else int(round(until_s * 1e9))
            return
        step = int(round(self.plan.clock_step_s * 1e9))
        self._limit_ns = 2**62 if until_s is None else int(round(until_s * 1e9 / step)) * step
        self._run_clock.set()

    def clock_reached(self) -> bool:
        """The clock is held at the requested time and every node has been handed that time:
        a service call after this (the camera's stop, which ends the capture at its own clock)
        reads the held time, not the step before it, which would drop the last frame. On the
        system clock: it has passed the requested time."""
        if not self.simulated_clock:
            return self.get_clock().now().nanoseconds >= self._limit_ns
        return (self._published_ns >= self._limit_ns
                and self._clock_pub.wait_for_all_acked(Duration(seconds=0.5)))

    def pause_clock(self) -> None:
        self._run_clock.clear()

    def service_names(self) -> tuple[str, ...]:
        return tuple(self.clients_)

    def service_ready(self, name: str) -> bool:
        return self.clients_[name].service_is_ready()

    def device_problems(self) -> list[str]:
        """The shaker and stage nodes not active (a device that did not open leaves its node
        unconfigured; its log says why), and a camera in error, one line each."""
        out = []
        for name, client in self._lifecycle.items():
            try:  # the first call to a node that has just started: asked again if unanswered
                label = ask(client, GetState.Request(), 30.0).current_state.label
            except RigError as e:
                out.append(f"{name}: {e}")
                continue
            if label != "active":
                out.append(f"{name}: the node is {label}, not active (its log says why)")
        if self.camera().get("state") == "error":
            out.append(f"camera: {self.camera().get('message')}")
        return out

    def design(self) -> dict | None:
        return self.latest.get("design")

    def camera(self) -> dict:
        return self.latest.get("camera") or {}

    def stage_state(self) -> str:
        return str(self.latest.get("stage", ""))

    def recorder(self) -> dict:
        return self.latest.get("recorder") or {}

    def recorder_subscribed(self, topics: tuple[str, ...]) -> bool:
        return all(any(i.node_name == "recorder" for i in self.get_subscriptions_info_by_topic(t))
                   for t in topics)

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        for st in msg.status:
            if st.name == "stage" and st.message.startswith("holding") and self._hold_ns is None:
                self._hold_ns = convert.to_ns(msg.header.stamp)
            elif st.name == "shaker" and st.message.startswith("fault: "):
                self._shaker_fault = st.message
            elif st.name == "shaker" and st.message.startswith("compensation "):
                values = {kv.key: kv.value for kv in st.values}
                self._compensation = (values.get("converged") == "True", st.message)

    def shaker_fault(self) -> str:
        return self._shaker_fault

    def compensation(self) -> tuple[bool, str] | None:
        return self._compensation

    def compensate(self, waveform: str, amplitude_m: float, frequency_hz: float,
                   cycles: float) -> tuple[bool, str]:
        self._compensation = None
        r = self.call("compensate", FirePulse.Request(
            waveform=waveform, amplitude_m=amplitude_m, frequency_hz=frequency_hz,
            cycles=cycles))
        return r.accepted, r.message

    def stage_hold_time(self) -> float | None:
        return None if self._hold_ns is None else self._hold_ns * 1e-9

    def set_strain(self, strain: float) -> tuple[bool, str]:
        self._hold_ns = None
        r = self.call("set_strain", SetStrain.Request(strain=strain))
        return r.accepted, r.message

    def fire(self, waveform: str, amplitude_m: float, frequency_hz: float, cycles: float,
             delay_s: float) -> tuple[bool, str]:
        r = self.call("fire", FirePulse.Request(waveform=waveform, amplitude_m=amplitude_m,
                                                frequency_hz=frequency_hz, cycles=cycles,
                                                delay_s=delay_s))
        return r.accepted, r.message

    def camera_start(self, t_start_s: float) -> bool:
        """Start the capture at simulated time `t_start_s` (the camera's own clock may lag the
        one held here under load and would start early: one to two extra frames were seen).
        A lab camera starts streaming when called (the system clock cannot be held)."""
        if self.simulated_clock and self._cam_params.service_is_ready():
            req = SetParameters.Request(parameters=[
                Parameter("capture_start_s", value=float(t_start_s)).to_parameter_msg()])
            fut = self._cam_params.call_async(req)
            until(fut.done, "the camera's parameters", 30.0)
            if not all(r.successful for r in fut.result().results):
                log.warning("the camera took no capture start time: it starts at its own clock")
        return self.call("cam_start", Trigger.Request()).success

    def camera_snapshot(self) -> tuple[bool, str]:
        r = self.call("cam_snapshot", Trigger.Request())
        return r.success, r.message

    def camera_stop(self) -> None:
        self.call("cam_stop", Trigger.Request())

    def recorder_start(self) -> None:
        self.call("rec_start", Trigger.Request())

    def recorder_stop(self, timeout_s: float = 30.0) -> dict | None:
        try:
            r = self.call("rec_stop", Trigger.Request(), timeout_s=timeout_s)
        except RigError as e:
            log.warning("%s", e)
            return None
        return json.loads(r.message) if r.success else None

    def stop_devices(self) -> None:
        """Bring the rig to rest: broadcast /rig/stop, then the stop services (best effort); a
        camera still streaming (a lab camera) is stopped too."""
        self._stop_pub.publish(Empty())
        names = ["shaker_stop", "stage_stop"]
        if self.camera().get("state") == "streaming":
            names.append("cam_stop")
        for name in names:
            try:
                self.call(name, Trigger.Request(), timeout_s=5.0)
            except RigError as e:
                log.warning("%s", e)
