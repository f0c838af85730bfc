"""Linear stage node (lifecycle): target strain in, stage positions and state out.

Interfaces (node name `stage`):
- service `~/set_strain` (metarig_msgs/srv/SetStrain): move to a strain and hold; refused
  outside the limits, in FAULT, when not active, or while a node not on `allowed_callers` has
  a client on it (`logic.command_guard`) (reason in `message`).
- services `~/stop` (hold where you are) and `~/reset` (clear a FAULT), std_srvs/Trigger;
  topic `/rig/stop` (std_msgs/Empty) stops too.
- `~/joint_states` (sensor_msgs/JointState: stage_bottom, stage_top; m toward the centre).
- `~/target_strain` (std_msgs/Float64, latched) and `~/state` (std_msgs/String, latched:
  idle / moving / holding / fault[: reason]); `/diagnostics` on every state change.
In FAULT the node samples the stages once per timer call (the newest due sample): a controller
that stopped answering costs a reply timeout per reading.
The stages are those of parameter `hardware`: "sim", or "lab" with `lab_file`
(`ros_nodes.hardware`); a lab file or controller that cannot be used fails the configure
transition with one logged line. With "lab" the lab file's limits hold: `device.*` changes at
run time do not reach the stages.
"""

import threading

import numpy as np
from metarig_msgs.srv import SetStrain
from rclpy.lifecycle import LifecycleNode, State, TransitionCallbackReturn
from std_msgs.msg import Empty, Float64, String
from std_srvs.srv import Trigger

from devices.lab import LabFileError
from devices.limits import DeviceError, LimitError
from devices.stage.port import StageCommand, StageMode, StagePair, check_strain
from ros_nodes import convert
from ros_nodes import topics as T
from ros_nodes.hardware import stage_pair
from ros_nodes.logic.sampling import due_samples
from ros_nodes.nodes._common import COMMAND, LATCHED, qos_profile, release_device, run_node
from ros_nodes.nodes._guard import motion_refusal
from ros_nodes.nodes._params import TypedParams
from ros_nodes.params import StageNodeConfig

NAME = "stage"


def _stages(cfg: StageNodeConfig, rng: np.random.Generator) -> StagePair:
    """The stages behind the port that `cfg.hardware` names ("sim", or "lab": `lab_file`)."""
    return stage_pair(cfg, rng)


class StageNode(LifecycleNode):
    """Thin adapter over the stage port (`devices.stage.port`; see module docstring)."""

    def __init__(self, **kwargs):
        super().__init__(NAME, **kwargs)
        self._params = TypedParams(self, StageNodeConfig, on_change=self._reconfigured)
        self._active = False
        self._stages: StagePair | None = None
        self._timer = None
        self._pubs: dict = {}
        self._last_mode = None
        self._device_lock = threading.Lock()  # the timer's readings vs close() (another thread)
        self.create_service(SetStrain, T.STAGE_SET_STRAIN.name, self._on_set_strain)
        self.create_service(Trigger, T.STAGE_STOP.name, self._on_stop)
        self.create_service(Trigger, T.STAGE_RESET.name, self._on_reset)
        self.create_subscription(Empty, T.RIG_STOP.name, lambda _m: self._stop(), COMMAND)
        if self._params.config.autostart and \
                self.trigger_configure() == TransitionCallbackReturn.SUCCESS:
            self.trigger_activate()

    def on_configure(self, state: State) -> TransitionCallbackReturn:
        cfg = self._params.config
        self._rng = np.random.default_rng(cfg.seed)
        self._pubs = {
            "js": self.create_publisher(convert.JointState, T.STAGE_JOINTS.name,
                                        qos_profile(T.STAGE_JOINTS.qos)),
            "target": self.create_publisher(Float64, T.STAGE_TARGET.name, LATCHED),
            "state": self.create_publisher(String, T.STAGE_STATE.name, LATCHED),
            "diag": self.create_publisher(convert.DiagnosticArray, T.DIAGNOSTICS.name, COMMAND),
        }
        try:
            self._stages = _stages(cfg, self._rng)
        except (LabFileError, DeviceError, ValueError, OSError) as e:
            self.get_logger().error(f"cannot configure the stages: {e}")
            self._pubs["diag"].publish(convert.diagnostics(
                self.get_clock().now().nanoseconds, NAME, "error",
                f"cannot configure the stages: {e}", {}))
            self.on_cleanup(state)  # back to unconfigured: a later configure starts afresh
            return TransitionCallbackReturn.FAILURE
        self._publish_mode(force=True)
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state: State) -> TransitionCallbackReturn:
        self._stages.start(self._now_s())
        self._timer = self.create_timer(1.0 / self._params.config.rate_hz, self._tick)
        self._active = True
        return super().on_activate(state)

    def on_deactivate(self, state: State) -> TransitionCallbackReturn:
        self._active = False
        self._stages.command(StageCommand(stop=True))
        self._tick()
        if self._timer is not None:
            self.destroy_timer(self._timer)
            self._timer = None
        return super().on_deactivate(state)

    def on_cleanup(self, state: State) -> TransitionCallbackReturn:
        for p in self._pubs.values():
            self.destroy_publisher(p)
        self._pubs = {}
        if self._stages is not None:
            self._stages.close()
            self._stages = None
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: State) -> TransitionCallbackReturn:
        self._active = False
        return TransitionCallbackReturn.SUCCESS

    def _reconfigured(self, cfg: StageNodeConfig) -> None:
        if self._stages is None:
            return
        if cfg.hardware == "lab":  # the lab file's limits stand
            self.get_logger().warning("hardware 'lab': the limits are the lab file's; device.* "
                                      "parameters do not change them")
            return
        self._stages.reconfigure(cfg.device)  # new limits hold from the next command

    def _now_s(self) -> float:
        return self.get_clock().now().nanoseconds * 1e-9

    def _tick(self) -> None:
        with self._device_lock:
            self._sample()

    def _sample(self) -> None:
        if self._stages is None:
            return
        cfg = self._params.config
        times = due_samples(self._stages.time_s, self._now_s(), 1.0 / cfg.rate_hz)
        if self._stages.status.mode == StageMode.FAULT:
            # in FAULT only the newest sample is taken: a controller that stopped answering
            # costs a reply timeout per reading, and catching up would never end
            times = times[-1:]
        for t in times:
            try:  # a command acts once, at the first sample after it came
                r = self._stages.read(t)
            except LimitError as e:  # cannot happen for checked commands; never kill the node
                self.get_logger().error(str(e))
                return
            if "js" in self._pubs:
                self._pubs["js"].publish(convert.stage_state(int(round(r.t * 1e9)), r.bottom_m,
                                                             r.top_m))
            self._publish_mode()
            if r.mode == StageMode.FAULT:
                break

    def _publish_mode(self, force: bool = False) -> None:
        s = self._stages.status
        label = s.mode.value + (f": {s.fault}" if s.fault else "")
        if not force and label == self._last_mode or "state" not in self._pubs:
            return
        self._last_mode = label
        self._pubs["state"].publish(String(data=label))
        self._pubs["target"].publish(convert.scalar(s.target_m
                                                    / self._stages.limits.sample_height_m))
        level = "error" if s.mode == StageMode.FAULT else "ok"
        # stamped with the sample at which the state changed (the node's clock may be later)
        self._pubs["diag"].publish(convert.diagnostics(
            int(round(s.t * 1e9)), NAME, level, label,
            {"closing_m": f"{s.closing_m:.6g}", "target_m": f"{s.target_m:.6g}"}))
        if s.mode == StageMode.FAULT:
            self.get_logger().error(f"FAULT: {s.fault}")

    def _on_set_strain(self, req, res):
        why = None if not self._active else motion_refusal(
            self, T.STAGE_SET_STRAIN.name, self._params.config.allowed_callers)
        if not self._active:
            res.accepted, res.message = False, "refused: the stage node is not active"
        elif why is not None:
            res.accepted, res.message = False, f"refused: {why}"
        elif self._stages.status.mode == StageMode.FAULT:
            res.accepted = False
            res.message = f"refused: stages in FAULT ({self._stages.status.fault})"
        else:
            try:  # the limits, before the stages hear of it
                check_strain(self._stages.limits, req.strain)
                self._stages.command(StageCommand(target_strain=req.strain))
                res.accepted, res.eta_s = True, self._stages.eta_s(req.strain)
                res.message = f"accepted: moving to strain {req.strain:g} (~{res.eta_s:.3g} s)"
            except LimitError as e:
                res.accepted, res.message = False, f"refused: {e}"
        if res.accepted:
            self.get_logger().info(res.message)
        else:
            self.get_logger().warning(res.message)
        return res

    def _stop(self) -> None:
        if self._stages is not None:
            self._stages.command(StageCommand(stop=True))
        self.get_logger().info("stop: holding position")

    def _on_stop(self, req, res):
        self._stop()
        res.success, res.message = True, "stopped: stages hold their position"
        return res

    def _on_reset(self, req, res):
        res.success = self._stages is not None and self._stages.status.mode == StageMode.FAULT
        if self._stages is not None:
            self._stages.command(StageCommand(reset=True))
        res.message = "fault cleared" if res.success else "nothing to reset (no fault)"
        return res

    def close(self) -> None:
        """Bring the stages to rest and release the device (the node is going down): a stop
        still pending (`/rig/stop` just before) reaches the stages now, then the port closes."""
        self._active = False
        with self._device_lock:
            if self._stages is not None:  # one reading sends it, due or not
                self._stages.command(StageCommand(stop=True))
                self._stages.read(max(self._now_s(), self._stages.time_s))
            self._timer = release_device(self, self._timer)


def main(args=None) -> int:
    return run_node(StageNode, args=args)


if __name__ == "__main__":
    raise SystemExit(main())
