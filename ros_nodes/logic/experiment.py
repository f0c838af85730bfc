"""The experiment procedure as pure logic behind a small port (no rclpy).

`Experiment.run()` takes the reference image of the unloaded sample, starts the recorder (so that
the recording holds the stage closing from rest), pre-compresses, settles, starts the camera,
fires the pulse, records for `record_s` and waits for the developed frames; `Experiment.finish()`
brings the rig to rest and closes the recording whatever happened. The rig is reached only
through a `RigPort`: `ros_nodes.nodes.sequencer_node.SequencerNode` implements it over ROS
services and topics, tests implement it with a fake rig. Every wait has a wall-time deadline,
and a wait that lasts says so every `PROGRESS_S` (what it waits for, for how long, and what
the rig reports meanwhile: the stage's state, the camera's frames). Nothing moves before every
device node has reported ready (`RigPort.device_problems`).
"""

import logging
import math
from collections.abc import Callable
from typing import Protocol

from ros_nodes import topics
from ros_nodes.logic.sequence import IMAGE_TOPIC, ExperimentPlan, Phase

log = logging.getLogger("metarig.rig")
POLL_S = 0.005  # how often a wait re-checks its condition, s (wall)
PROGRESS_S = 2.0  # a wait longer than this logs a progress line this often, s (wall)
# the measured device motion must reach the end of the capture (the comparison's input); a
# device samples at its own rate, so its last sample may be up to a period earlier
DEVICE_TOPICS = (topics.SHAKER_JOINTS.name, topics.STAGE_JOINTS.name)
DEVICE_SLACK_S = 0.05


def _capturing(status: dict) -> bool:
    """The camera films: the simulated one from its start, a lab one once a frame came."""
    return status.get("state") == "capturing" or (status.get("state") == "streaming"
                                                  and status.get("frames", 0) > 0)


class RigError(RuntimeError):
    """The experiment could not proceed (a refusal, a fault or a timeout); message says why."""


class RigPort(Protocol):
    """What the procedure needs from the rig. Calls that wait for an answer raise `RigError`
    on timeout; `(accepted, message)` pairs carry a device's refusal and its reason."""

    def now(self) -> float:
        """Wall time (monotonic), s."""

    def sleep(self, dt_s: float) -> None:
        """Wait `dt_s` of wall time."""

    def sim_time(self) -> float:
        """Current simulated time, s."""

    def announce(self, phase: Phase) -> None:
        """Publish the phase the experiment entered."""

    def start_clock(self, until_s: float | None) -> None:
        """Run simulated time up to `until_s` (rounded to the clock step; None: no limit)."""

    def clock_reached(self) -> bool:
        """Whether simulated time has reached the limit of the last `start_clock`."""

    def pause_clock(self) -> None:
        """Hold simulated time."""

    def service_names(self) -> tuple[str, ...]:
        """Names of the rig services the procedure calls."""

    def service_ready(self, name: str) -> bool:
        """Whether service `name` is available."""

    def device_problems(self) -> list[str]:
        """Why a device cannot be used (a device node not active, a camera in error), one
        line each; empty when every device is ready."""

    def design(self) -> dict | None:
        """The specimen's design (`/rig/design`) once the camera has built it."""

    def camera(self) -> dict:
        """The camera's last status (`state`, `frames`, `message`; {} before the first)."""

    def stage_state(self) -> str:
        """The stage's last state string (`idle`, `moving`, `holding`, `fault: why`; '')."""

    def shaker_fault(self) -> str:
        """The shaker's last fault (`fault: why`: a drive that failed on its own and was told
        to stop, e.g. a function generator's instrument error or lost connection; '')."""

    def compensation(self) -> tuple[bool, str] | None:
        """The outcome of the last `compensate`: (within the tolerances, the shaker's line);
        None while it runs."""

    def stage_hold_time(self) -> float | None:
        """Simulated time of the stage sample at which the stages began to hold their target
        (None: not known)."""

    def recorder_subscribed(self, topics: tuple[str, ...]) -> bool:
        """Whether the recorder has a subscription on each of `topics` (it subscribes to a
        topic once it has discovered a publisher of it)."""

    def recorder(self) -> dict:
        """The recorder's last status (`recording`, `matched`, `counts`, `last_stamp_s` per
        topic; {} before the first)."""

    def set_strain(self, strain: float) -> tuple[bool, str]: ...

    def fire(self, waveform: str, amplitude_m: float, frequency_hz: float, cycles: float,
             delay_s: float) -> tuple[bool, str]: ...

    def compensate(self, waveform: str, amplitude_m: float, frequency_hz: float,
                   cycles: float) -> tuple[bool, str]:
        """Start the shaker's drive compensation for this request (`compensation` says when
        it is over)."""

    def camera_start(self, t_start_s: float) -> bool:
        """Start the camera's capture window at simulated time `t_start_s` (the time held)."""

    def camera_snapshot(self) -> tuple[bool, str]:
        """Publish one frame now as the tracker's reference image (`/camera/reference_image`)."""

    def camera_stop(self) -> None: ...

    def recorder_start(self) -> None: ...

    def recorder_stop(self, timeout_s: float) -> dict | None:
        """Finish the recording; its loss report (None: no answer or not recording)."""

    def stop_devices(self) -> None:
        """Broadcast the rig stop and call the devices' stop services (best effort)."""


class Experiment:
    """One run of `plan` against `port`; `events` lists (phase, simulated time s)."""

    def __init__(self, plan: ExperimentPlan, port: RigPort):
        self.plan = plan
        self.port = port
        self.events: list[tuple[str, float]] = []
        self.compensation = ""  # the shaker's compensation outcome (plan.compensate)

    # helpers ----------------------------------------------------------------------------------
    def phase(self, p: Phase) -> None:
        t = self.port.sim_time()
        self.events.append((p.value, t))
        self.port.announce(p)
        # rig time from the first phase: 0 on the simulated clock, the run's start on the
        # system clock (run.json keeps the absolute times)
        log.info("phase %-11s t = %.4f s", p.value, t - self.events[0][1])

    def until(self, predicate: Callable[[], object], what: str,
              timeout_s: float | None = None,
              fault: Callable[[], str | None] | None = None) -> None:
        """Wait until `predicate()` is true; `RigError` after `timeout_s` (plan default), or as
        soon as `fault()` names one; a progress line every `PROGRESS_S` while it waits."""
        port = self.port
        start = port.now()
        deadline = start + (timeout_s or self.plan.timeout_s)
        next_note = start + PROGRESS_S
        while not predicate():
            why = fault() if fault is not None else None
            if why:
                raise RigError(why)
            now = port.now()
            if now > deadline:
                raise RigError(f"timed out waiting for {what}")
            if now >= next_note:
                log.info("waiting %.0f s for %s (%s)", now - start, what, self._progress())
                next_note = now + PROGRESS_S
            port.sleep(POLL_S)

    def _progress(self) -> str:
        """What the rig reports now: stage state, camera state and frames, recorded messages."""
        port = self.port
        cam, rec = port.camera(), port.recorder()
        parts = [f"stage {port.stage_state() or '?'}",
                 f"camera {cam.get('state', '?')} {cam.get('frames', 0)} frames"]
        if rec.get("recording"):
            parts.append(f"{sum(rec.get('counts', {}).values())} messages recorded")
        return ", ".join(parts)

    def run_clock_until(self, t_s: float) -> None:
        """Run simulated time up to exactly `t_s` (rounded to the clock step), then hold it;
        on the system clock, wait until it has passed `t_s`. A stage fault or a camera error
        meanwhile (a device that stopped answering) ends the run (`RigError`)."""
        self.port.start_clock(t_s)
        self.until(self.port.clock_reached,
                   f"rig time {t_s - (self.events[0][1] if self.events else 0.0):.4f} s",
                   fault=self._device_fault)
        self.port.pause_clock()

    def _device_fault(self) -> str | None:
        """A stage in FAULT, a shaker fault or a camera in error, as one line (None: all
        well)."""
        stage, cam, shaker = self.port.stage_state(), self.port.camera(), self.port.shaker_fault()
        if stage.startswith("fault"):
            return f"stage {stage}"
        if shaker:
            return f"shaker {shaker}"
        if cam.get("state") == "error":
            return f"camera: {cam.get('message')}"
        return None

    # the procedure ----------------------------------------------------------------------------
    def run(self) -> dict:
        """Run the experiment; returns wall timings (s) and `frames`. Raises `RigError`
        (call `finish` in any case)."""
        p, port = self.plan, self.port
        w0 = port.now()
        self.phase(Phase.STARTING)
        self.until(lambda: port.design() is not None or port.camera().get("state") == "error",
                   "the specimen to be built (/rig/design)")
        if port.camera().get("state") == "error":
            raise RigError(f"camera: {port.camera().get('message')}")
        # 120 s: a live tracker offers its service once its kernels are compiled, which a cold
        # cache on a busy host makes take a minute
        for name in port.service_names():
            self.until(lambda n=name: port.service_ready(n), f"service {name}", 120.0)
        problems = port.device_problems()
        if problems:  # before anything moves
            raise RigError("; ".join(problems))
        if p.compensate:
            self.compensate()
        # the unloaded sample: the tracker finds every unit of the pre-compressed first frame
        # against it, so that poses are from the unloaded design (as the simulation's)
        ok, why = port.camera_snapshot()
        if not ok:
            log.warning("no reference image of the unloaded sample (%s): poses will be tracked "
                        "from the first recorded frame, which is already pre-compressed", why)
        # the recorder's `matched` covers the topics it has discovered: with one process per
        # node under load it had once not yet discovered the shaker node when the run started,
        # and recorded none of its motion
        self.until(lambda: port.recorder_subscribed(DEVICE_TOPICS),
                   "the recorder to subscribe to the shaker's and the stage's motion", 30.0)
        # the recording holds the whole test from rest: the stage closing as the stages made it
        # (the comparison and the simulated camera then start from the same history)
        port.recorder_start()
        # recording, and subscribed to every rig topic: a sample sent before the match is lost
        self.until(lambda: port.recorder().get("recording") and
                   port.recorder().get("matched", True),
                   "the recorder to start and match every topic", 30.0)
        timings = {"startup": port.now() - w0}

        w = port.now()
        self.phase(Phase.PRECOMPRESS)
        ok, why = port.set_strain(p.strain)
        if not ok:
            raise RigError(f"stage: {why}")
        port.start_clock(None)
        self.until(lambda: port.stage_state().startswith(("holding", "fault"))
                   or (p.strain == 0 and port.sim_time() > 0.005),
                   "the stages to reach the strain")
        if port.stage_state().startswith("fault"):
            raise RigError(f"stage {port.stage_state()}")
        self.phase(Phase.SETTLE)
        # the settle is timed from the stage's own hold sample, not from when the hold was seen
        # here (later under load, which shifted everything after it by a clock step or two)
        if port.stage_state().startswith("holding"):
            self.until(lambda: port.stage_hold_time() is not None, "the stage's hold time", 10.0)
        t_hold = port.stage_hold_time()
        start = port.sim_time() if t_hold is None else t_hold
        self.run_clock_until(max(port.sim_time(), start + p.settle_s))
        timings["precompress_settle"] = port.now() - w

        w = port.now()
        port.pause_clock()
        self.phase(Phase.RECORD)
        t_rec = port.sim_time()
        if not port.camera_start(t_rec):
            raise RigError("camera refused to start")
        # a camera on the system clock (a lab's) can take a while for its first frame on a busy
        # host: the pulse waits for it, so that the footage holds the pulse from its start (the
        # simulated camera films simulated time, which stands still meanwhile)
        self.until(lambda: _capturing(port.camera()), "the camera's first frame", 10.0,
                   fault=self._device_fault)
        t_rec = port.sim_time()
        ok, why = port.fire(p.waveform, p.amplitude_m, p.frequency_hz, p.cycles, p.pre_trigger_s)
        if not ok:
            raise RigError(f"shaker: {why}")
        self.phase(Phase.PULSE)
        self.run_clock_until(t_rec + p.record_s)
        timings["record_live"] = port.now() - w

        w = port.now()
        self.phase(Phase.DEVELOP)
        t_end = port.sim_time()
        port.camera_stop()
        self.until(lambda: port.camera().get("state") in ("done", "error"), "the camera footage")
        cam = port.camera()
        if cam["state"] == "error":
            raise RigError(f"camera: {cam.get('message')}")
        n = int(cam["frames"])
        try:
            self.until(lambda: port.recorder().get("counts", {}).get(IMAGE_TOPIC, 0) >= n,
                       f"the recorder to write {n} frames", 30.0)
        except RigError as e:
            log.warning("%s; finishing with what arrived (the report counts the loss)", e)
        try:  # a busy host delivers the device samples late: they are still on their way
            self.until(lambda: self._devices_recorded(t_end - DEVICE_SLACK_S),
                       "the recorder to hold the shaker and stage motion to the end of the "
                       "capture", 30.0)
        except RigError as e:
            log.warning("%s; finishing with what arrived", e)
        timings["develop_publish"] = port.now() - w
        timings["frames"] = n
        if "lost" in cam:  # a real camera: frames its own frame counter says never came
            timings["camera_lost"] = int(cam["lost"])
        if "received" in cam:  # ... and those the driver delivered to the node
            timings["camera_received"] = int(cam["received"])
        return timings

    def compensate(self) -> None:
        """Have the shaker compensate its drive for the plan's pulse (trial drives played
        and measured by the shaker on the rig clock, before the recording starts)."""
        p, port = self.plan, self.port
        self.phase(Phase.COMPENSATE)
        ok, why = port.compensate(p.waveform, p.amplitude_m, p.frequency_hz, p.cycles)
        if not ok:
            raise RigError(f"shaker: {why}")
        log.info("shaker: %s", why)
        port.start_clock(None)
        self.until(lambda: port.compensation() is not None, "the shaker's drive compensation",
                   fault=self._device_fault)
        port.pause_clock()
        converged, line = port.compensation()
        if line.startswith("compensation failed"):
            raise RigError(f"shaker: {line}")
        self.compensation = line
        if converged:
            log.info("shaker: %s", line)
        else:  # the best drive within the limits is still played; the line says how far off
            log.warning("shaker: %s", line)

    def _devices_recorded(self, t_s: float) -> bool:
        last = self.port.recorder().get("last_stamp_s", {})
        return all(last.get(t, -math.inf) >= t_s for t in DEVICE_TOPICS)

    def finish(self, completed: bool, recorder_timeout_s: float = 30.0) -> dict | None:
        """Stop the devices, finish the recording; returns the recorder's report (or None)."""
        self.phase(Phase.STOP)
        self.port.pause_clock()
        self.port.stop_devices()
        report = self.port.recorder_stop(recorder_timeout_s)
        self.phase(Phase.DONE if completed else Phase.ABORTED)
        return report
