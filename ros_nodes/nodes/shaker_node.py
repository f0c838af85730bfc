"""Shaker command node (lifecycle): pulse requests in, commanded waveform and measured motion out.

Interfaces (node name `shaker`):
- service `~/fire` (metarig_msgs/srv/FirePulse): play a waveform; refused outside the limits,
  when the drive refuses it (a function generator: volts over max_volts, an instrument error),
  when the node is not active, or while a node not on `allowed_callers` has a client on it
  (`logic.command_guard`), with the reason in `message`.
- service `~/compensate` (metarig_msgs/srv/FirePulse, guarded as `~/fire`): iterate the drive
  of a pulse or burst against the drive's own sensor (`devices.shaker.compensation`): the
  drives are played `compensation.rest_s` apart on the rig clock and measured at `rate_hz`
  from the readings the node publishes; the outcome is a `/diagnostics` line `compensation
  done: ...` or `compensation failed: ...`. A later `~/fire` of the same request plays the
  compensated drive (checked against the limits again). Refused for a drive that measures
  nothing (a function generator: its readings are the commanded motion).
- service `~/stop` (std_srvs/Trigger) and topic `/rig/stop` (std_msgs/Empty): drop the program
  (and a compensation under way), the actuator returns to rest at zero.
- `~/command` (trajectory_msgs/JointTrajectory, latched): the accepted waveform, absolute start
  (published after the request's answer, off the device lock: `DeviceNode._publish_later`).
- `~/joint_states` (sensor_msgs/JointState): measured displacement and velocity at `rate_hz`.
- `/diagnostics`: accepted / refused / stopped / finished events, and `fault: ...` (error) once
  when the drive reports a fault of its own (a function generator's watchdog: an instrument
  error or a lost connection; the drive has turned its output off as far as it could).
Transitions: configure creates the publishers and the device (parameter `hardware`: "sim", or
"lab" with `lab_file`, `ros_nodes.hardware`; a lab file or device that cannot be used fails the
transition with one logged line); activate starts the device clock; deactivate stops any
program; cleanup releases everything. With `hardware` "lab" the lab file's limits hold:
`device.*` changes at run time do not reach the drive.
"""

import numpy as np
from metarig_msgs.srv import FirePulse
from std_srvs.srv import Trigger

from devices.limits import DeviceError, LimitError
from devices.shaker.compensation import CompensationResult, Compensator, DriveTrials, \
    drive_waveform
from devices.shaker.port import ShakerDrive, prepare
from devices.shaker.waveform import WaveformRequest
from ros_nodes import convert
from ros_nodes import topics as T
from ros_nodes.hardware import shaker_drive
from ros_nodes.logic.sampling import due_samples
from ros_nodes.nodes._common import LATCHED, qos_profile, run_node
from ros_nodes.nodes._device_node import DeviceNode
from ros_nodes.nodes._guard import motion_refusal
from ros_nodes.params import ShakerNodeConfig


class ShakerNode(DeviceNode):
    """Thin adapter over the shaker port (`devices.shaker.port`; see module docstring); the
    lifecycle is `DeviceNode`'s."""

    NAME, CONFIG, DEVICE = "shaker", ShakerNodeConfig, "the shaker"

    def __init__(self, **kwargs):
        self._playing_until: float | None = None  # rig time the accepted waveform ends, s
        self._trials: DriveTrials | None = None  # a compensation under way ...
        self._trial_request: WaveformRequest | None = None  # ... of this request
        self._compensated: tuple[WaveformRequest, CompensationResult] | None = None
        self._fault = ""  # the drive's fault, once reported
        super().__init__(**kwargs)

    @property
    def _drive(self) -> ShakerDrive | None:
        return self._device

    # DeviceNode hooks --------------------------------------------------------------------
    def _device_services(self) -> list[tuple]:
        return [
            (FirePulse, T.SHAKER_FIRE.name, self._on_fire),
            (Trigger, T.SHAKER_STOP.name, self._on_stop),
            (FirePulse, T.SHAKER_COMPENSATE.name, self._on_compensate),
        ]

    def _create_publishers(self) -> dict:
        return {
            "js": self.create_publisher(convert.JointState, T.SHAKER_JOINTS.name,
                                        qos_profile(T.SHAKER_JOINTS.qos)),
            "cmd": self.create_publisher(convert.JointTrajectory, T.SHAKER_COMMAND.name, LATCHED),
        }

    def _open(self, cfg: ShakerNodeConfig, rng: np.random.Generator) -> ShakerDrive:
        return shaker_drive(cfg, rng)

    def _configured(self) -> None:
        self._report("ok", "configured")

    def _activated(self) -> None:
        self._report("ok", "active")

    def _deactivated(self) -> None:
        self._report("ok", "inactive")

    def _halt(self) -> None:
        self._drop_program()

    def _rig_stop(self) -> None:
        self._stop("rig stop")

    def _diag_values(self) -> dict:
        return {"active": self._active, "playing": self._playing_until is not None}

    def _sample(self) -> None:
        cfg = self._params.config
        for t in due_samples(self._drive.time_s, self._now_s(), 1.0 / cfg.rate_hz):
            r = self._drive.read(t)
            self._pubs["js"].publish(convert.shaker_state(int(round(r.t * 1e9)), r.x_m,
                                                          r.v_m_s))
            if self._trials is not None:
                self._trial_reading(r.t, r.x_m)
        if self._playing_until is not None and self._drive.time_s > self._playing_until:
            self._playing_until = None
            self._report("ok", "waveform finished")
        self._check_fault()

    # callbacks ---------------------------------------------------------------------------
    def _check_fault(self) -> None:
        """Report a fault the drive found on its own, once (it has stopped its output)."""
        fault = self._drive.fault
        if fault and fault != self._fault:
            self._playing_until, self._trials = None, None
            self.get_logger().error(f"fault: {fault}")
            self._report("error", f"fault: {fault}")
        self._fault = fault

    def _trial_reading(self, t_s: float, x_m: float) -> None:
        """A reading during a compensation: filed; the next drive played, or the outcome."""
        try:
            result = self._trials.take(t_s, x_m)
            if result is None and self._trials.pending:
                self._drive.play(*self._trials.play())
        except (ValueError, LimitError, DeviceError) as e:
            self._trials = None
            self.get_logger().error(f"compensation failed: {e}")
            self._report("error", f"compensation failed: {e}")
            return
        if result is not None:
            self._trials = None
            self._compensated = (self._trial_request, result)
            p, r = result.peak_errors, result.rms_errors
            text = (f"compensation done: {len(p)} drives, measured peak error {p[0]:+.2%} -> "
                    f"{p[-1]:+.2%}, RMS error {r[0]:.2%} -> {r[-1]:.2%} ({result.stopped}); "
                    f"measured by {self._drive.sensor}")
            self.get_logger().info(text)
            self._report("ok" if result.converged else "warn", text,
                         {"converged": result.converged, "peak_errors": list(p),
                          "rms_errors": list(r), "drive_peaks_m": list(result.drive_peaks_m)})

    def _on_fire(self, req, res):
        if not self._active:
            res.accepted, res.message = False, "refused: the shaker node is not active"
            self.get_logger().warning(res.message)
            return res
        why = motion_refusal(self, T.SHAKER_FIRE.name, self._params.config.allowed_callers)
        if why is not None:
            res.accepted, res.message = False, f"refused: {why}"
            self.get_logger().warning(res.message)
            self._report("warn", res.message)
            return res
        busy = self._busy()
        if busy:
            res.accepted, res.message = False, f"refused: {busy}"
            self.get_logger().warning(res.message)
            self._report("warn", res.message)
            return res
        request = _request(req)
        cfg = self._params.config
        try:  # the limits, before the drive hears of it (a compensated drive checked again)
            wf = prepare(self._drive.limits, request, req.delay_s)
            drive, note = wf, ""
            if self._compensated is not None and self._compensated[0] == request:
                kept = self._compensated[1]
                drive = drive_waveform(self._drive.limits, kept.drive.samples_m,
                                       kept.drive.sample_rate_hz)
                note = (f", compensated drive of {drive.amplitude_m:g} m peak (measured peak "
                        f"error {kept.peak_errors[-1]:+.2%} after {len(kept.peak_errors)} "
                        "drives)")
        except LimitError as e:
            return self._refused(res, e)
        start_ns = self.get_clock().now().nanoseconds + int(round(req.delay_s * 1e9))
        try:  # a drive's own refusals: volts over its limit, an instrument error
            self._drive.play(drive, start_ns * 1e-9)
        except (LimitError, DeviceError) as e:
            return self._refused(res, e)
        self._playing_until = start_ns * 1e-9 + drive.duration_s
        ts = np.arange(0.0, drive.duration_s + 0.5 / cfg.command_rate_hz,
                       1.0 / cfg.command_rate_hz)
        u, v = drive.displacement(ts), drive.velocity(ts)
        self._publish_later("cmd", lambda: convert.command_trajectory(start_ns, ts, u, v))
        res.accepted = True
        res.message = (f"accepted: {wf.kind} A={wf.amplitude_m:g} m f={wf.frequency_hz:g} Hz, "
                       f"{wf.duration_s:.4g} s{note}")
        res.start = convert.stamp(start_ns)
        res.duration_s = drive.duration_s
        self.get_logger().info(res.message)
        self._report("ok", res.message)
        return res

    def _busy(self) -> str:
        """Why the shaker cannot take a motion request now ("" if it can)."""
        if self._trials is not None:
            return "the drive is being compensated"
        if self._playing_until is not None:
            return "a waveform is already playing"
        return ""

    def _on_compensate(self, req, res):
        why = "the shaker node is not active" if not self._active else \
            motion_refusal(self, T.SHAKER_COMPENSATE.name, self._params.config.allowed_callers)
        why = why or self._busy()
        if not why and not self._drive.sensor:
            why = ("the drive measures nothing (its readings are the commanded motion, as a "
                   "function generator's): nothing to compensate against")
        if why:
            res.accepted, res.message = False, f"refused: {why}"
            self.get_logger().warning(res.message)
            self._report("warn", res.message)
            return res
        cfg = self._params.config
        request = _request(req)
        try:
            wf = prepare(self._drive.limits, request, req.delay_s)
            comp = Compensator(wf, self._drive.limits, cfg.rate_hz, cfg.compensation)
        except (LimitError, ValueError) as e:
            return self._refused(res, e)
        trials = DriveTrials(comp, self._now_s() + max(req.delay_s, 1.0 / cfg.rate_hz))
        try:
            self._drive.play(*trials.play())
        except (LimitError, DeviceError) as e:
            return self._refused(res, e)
        self._compensated, self._trials, self._trial_request = None, trials, request
        c = cfg.compensation
        window_s = comp.times_s[-1]
        res.accepted = True
        res.message = (f"compensating: {wf.kind} A={wf.amplitude_m:g} m f={wf.frequency_hz:g} "
                       f"Hz, at most {c.max_iterations} drives of {window_s:.4g} s, "
                       f"{c.rest_s:g} s apart; measured by {self._drive.sensor}")
        res.start = convert.stamp(int(round(trials.start_s * 1e9)))
        res.duration_s = c.max_iterations * (window_s + c.rest_s)
        self.get_logger().info(res.message)
        self._report("ok", res.message)
        return res

    def _refused(self, res, e: Exception):
        """Refuse a request the drive would not play; after a device error, the drive is told
        to stop (its output off), as far as it still answers."""
        res.accepted, res.message = False, f"refused: {e}"
        if isinstance(e, DeviceError) and self._drive is not None:
            self.get_logger().error(res.message)
            self._report("error", res.message)
            try:
                self._drive.stop()
            except (DeviceError, OSError) as stop_error:
                self.get_logger().error(f"and the drive did not stop: {stop_error}")
        else:
            self.get_logger().warning(res.message)
            self._report("warn", res.message)
        return res

    def _on_stop(self, req, res):
        self._stop("stop service")
        res.success, res.message = True, "stopped: program dropped, actuator returning to rest"
        return res

    def _drop_program(self) -> None:
        self._playing_until = None
        if self._trials is not None:
            self._trials = None
            self._report("warn", "compensation failed: stopped before it ended")
        if self._drive is not None:
            try:
                self._drive.stop()
            except (DeviceError, OSError) as e:  # the other stops still go ahead
                self.get_logger().error(f"the drive did not stop: {e}")
                self._report("error", f"the drive did not stop: {e}")

    def _stop(self, why: str) -> None:
        self._drop_program()
        self.get_logger().info(f"stop ({why})")
        self._report("ok", f"stopped ({why})")


def _request(req) -> WaveformRequest:
    """The waveform request of a FirePulse request (unchecked)."""
    return WaveformRequest(kind=req.waveform or "pulse", amplitude_m=req.amplitude_m,
                           frequency_hz=req.frequency_hz, cycles=req.cycles or 1.0,
                           samples_m=tuple(req.samples_m), sample_rate_hz=req.sample_rate_hz)


def main(args=None) -> int:
    return run_node(ShakerNode, args=args)


if __name__ == "__main__":
    raise SystemExit(main())
