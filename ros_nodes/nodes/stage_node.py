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

import numpy as np
from metarig_msgs.srv import SetStrain
from std_msgs.msg import Float64, String
from std_srvs.srv import Trigger

from devices.limits import LimitError
from devices.stage.port import StageCommand, StageMode, StagePair, check_strain
from ros_nodes import convert
from ros_nodes import topics as T
from ros_nodes.hardware import stage_pair
from ros_nodes.logic.sampling import MAX_CATCH_UP, due_samples
from ros_nodes.nodes._common import LATCHED, qos_profile, run_node
from ros_nodes.nodes._device_node import DeviceNode
from ros_nodes.nodes._guard import motion_refusal
from ros_nodes.params import StageNodeConfig

class StageNode(DeviceNode):
    """Thin adapter over the stage port (`devices.stage.port`; see module docstring); the
    lifecycle is `DeviceNode`'s."""

    NAME, CONFIG, DEVICE = "stage", StageNodeConfig, "the stages"

    def __init__(self, **kwargs):
        self._last_mode = None
        super().__init__(**kwargs)

    @property
    def _stages(self) -> StagePair | None:
        return self._device

    # DeviceNode hooks --------------------------------------------------------------------
    def _device_services(self) -> list[tuple]:
        return [
            (SetStrain, T.STAGE_SET_STRAIN.name, self._on_set_strain),
            (Trigger, T.STAGE_STOP.name, self._on_stop),
            (Trigger, T.STAGE_RESET.name, self._on_reset),
        ]

    def _create_publishers(self) -> dict:
        return {
            "js": self.create_publisher(convert.JointState, T.STAGE_JOINTS.name,
                                        qos_profile(T.STAGE_JOINTS.qos)),
            "target": self.create_publisher(Float64, T.STAGE_TARGET.name, LATCHED),
            "state": self.create_publisher(String, T.STAGE_STATE.name, LATCHED),
        }

    def _open(self, cfg: StageNodeConfig, rng: np.random.Generator) -> StagePair:
        return stage_pair(cfg, rng)

    def _configured(self) -> None:
        self._publish_mode(force=True)

    def _halt(self) -> None:
        if self._stages is not None:
            self._stages.command(StageCommand(stop=True))

    def _deactivated(self) -> None:
        self._tick()  # the stop acts at the next sample: take it now

    def _rig_stop(self) -> None:
        self._stop()

    def _closing(self) -> None:
        if self._stages is not None:  # one reading sends a pending stop, due or not
            self._stages.command(StageCommand(stop=True))
            self._stages.read(max(self._now_s(), self._stages.time_s))

    def _sample(self) -> None:
        cfg = self._params.config
        # in FAULT only the newest sample is taken: a controller that stopped answering costs a
        # reply timeout per reading, and catching up would never end
        newest = 1 if self._stages.status.mode == StageMode.FAULT else MAX_CATCH_UP
        times = due_samples(self._stages.time_s, self._now_s(), 1.0 / cfg.rate_hz, newest)
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
            int(round(s.t * 1e9)), self.NAME, level, label,
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
        self._halt()
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


def main(args=None) -> int:
    return run_node(StageNode, args=args)


if __name__ == "__main__":
    raise SystemExit(main())
