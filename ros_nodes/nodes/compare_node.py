"""Comparison node: the experiment against its simulation, live or from a replayed recording.

Interfaces (node name `comparison`):
- subscribes `/dic/poses` (metarig_msgs/UnitPose2DArray), `/shaker/joint_states` and
  `/stage/joint_states` (sensor_msgs/JointState), `/stage/state`, and the latched
  `/rig/design`, `/rig/config`, `/rig/phase` (std_msgs/String); callbacks only hand the values
  to `ros_nodes.logic.compare_session.CompareSession`;
- service `/compare/run` (std_srvs/Trigger): compare what has been heard (the response says
  whether it started, or the one-line reason it cannot); with `auto`, `/rig/phase` = stop or
  done starts it too. The simulation (seconds) runs in a worker thread, never in a callback;
- publishes `/compare/result` (metarig_msgs/ComparisonResult, latched), `/compare/summary`
  (summary JSON, latched), `/compare/simulated_poses` (simulated poses at the frame times) and
  a `/diagnostics` status named `comparison`: ok with the metrics, or error with the reason;
  a running recorder writes them into the run's MCAP;
- with `out_dir`: summary.json, comparison.rrd (Rerun), the PNG plots and the trajectories,
  written by the functions `metarig compare` uses.
The stages' `holding` time is this node's clock at receipt (rig time under `use_sim_time`), as
the recorder logs it. Parameters: `ros_nodes.params.CompareNodeConfig`.
"""

import threading
import time
from pathlib import Path

from diagnostic_msgs.msg import DiagnosticArray
from metarig_msgs.msg import ComparisonResult, UnitPose2DArray
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from std_srvs.srv import Trigger

from ros_nodes import convert
from ros_nodes import topics as T
from ros_nodes.logic import comparison_run as run
from ros_nodes.logic.compare_session import CompareSession
from ros_nodes.logic.comparison_run import CompareError, velocity_text
from ros_nodes.logic.recording import stamp_s, total_closing_m
from ros_nodes.nodes._common import qos_profile, run_node
from ros_nodes.nodes._params import TypedParams
from ros_nodes.params import CompareNodeConfig

NAME = "comparison"
STREAM_DEPTH = 1000  # subscription queue of the streams: replays arrive in bursts


class CompareNode(Node):
    """Adapter: rig topics -> `CompareSession` -> comparison topics and files."""

    def __init__(self, **kwargs):
        super().__init__(NAME, **kwargs)
        self._params = TypedParams(self, CompareNodeConfig, on_change=self._on_params)
        self._session = CompareSession(self._params.config.min_frames, T.POSES.name)
        self._busy = threading.Lock()  # held by the worker while it compares
        self._worker: threading.Thread | None = None
        self._closing = False
        self._pubs = {t.name: self.create_publisher(cls, t.name, qos_profile(t.qos))
                      for t, cls in ((T.COMPARE_RESULT, ComparisonResult),
                                     (T.COMPARE_SUMMARY, String),
                                     (T.COMPARE_SIMULATED, UnitPose2DArray),
                                     (T.DIAGNOSTICS, DiagnosticArray))}
        for topic, cls, callback in (
                (T.POSES, UnitPose2DArray, self._session.add_poses),
                (T.SHAKER_JOINTS, JointState, self._on_shaker),
                (T.STAGE_JOINTS, JointState, self._on_stage),
                (T.STAGE_STATE, String, self._on_stage_state),
                (T.RIG_DESIGN, String, self._on_design),
                (T.RIG_CONFIG, String, self._on_config),
                (T.RIG_PHASE, String, self._on_phase)):
            depth = None if topic.qos.latched else max(topic.qos.depth, STREAM_DEPTH)
            self.create_subscription(cls, topic.name, callback, qos_profile(topic.qos, depth))
        self.create_service(Trigger, T.COMPARE_RUN.name, self._on_run)
        self.get_logger().info(f"listening for poses on {T.POSES.name}; compare with "
                               f"{T.COMPARE_RUN.name}" + (" or at the end of the experiment"
                                                          if self._params.config.auto else ""))

    # callbacks: hand over the values, return ----------------------------------------------------
    def _on_params(self, cfg: CompareNodeConfig) -> None:
        self._session.min_frames = cfg.min_frames

    def _on_shaker(self, msg: JointState) -> None:
        if len(msg.position):
            self._session.add_shaker(stamp_s(msg), float(msg.position[0]))

    def _on_stage(self, msg: JointState) -> None:
        if len(msg.position):
            self._session.add_stage(stamp_s(msg), total_closing_m(msg.position))

    def _on_stage_state(self, msg: String) -> None:
        self._session.stage_state(msg.data, self.get_clock().now().nanoseconds * 1e-9)

    def _on_design(self, msg: String) -> None:
        try:
            self._session.set_design(msg.data)
        except CompareError as e:
            self.get_logger().error(f"{T.RIG_DESIGN.name}: {e}")

    def _on_config(self, msg: String) -> None:
        try:
            self._session.set_config(msg.data)
        except CompareError as e:
            self.get_logger().error(f"{T.RIG_CONFIG.name}: {e}")

    def _on_phase(self, msg: String) -> None:
        if self._session.phase(msg.data) and self._params.config.auto:
            _started, text = self._start()
            self.get_logger().info(f"phase {msg.data}: {text}")

    def _on_run(self, _req, res):
        res.success, res.message = self._start()
        return res

    # the comparison -------------------------------------------------------------------------
    def _start(self) -> tuple[bool, str]:
        """Start the worker; (started, what happened)."""
        reason = self._session.refusal()
        if reason is not None:
            self._refuse(reason)
            return False, reason
        if not self._busy.acquire(blocking=False):
            return False, "a comparison is already running"
        n = self._session.n_frames
        self._worker = threading.Thread(target=self._work, name="compare", daemon=True)
        self._worker.start()
        return True, f"comparing {n} frames with the simulation"

    def _work(self) -> None:
        try:
            t_start = time.perf_counter()
            try:
                res = self._session.compare()
            except CompareError as e:
                self._refuse(str(e))
                return
            except Exception as e:  # noqa: BLE001 - the node must survive any input
                self.get_logger().error(f"comparison failed: {e!r}")
                self._refuse(f"comparison failed: {type(e).__name__}: {e}")
                return
            summary = res.summary
            summary["timings_s"] = {"total": time.perf_counter() - t_start}
            if self._closing:
                return
            for topic, _ns, msg in convert.comparison_messages(res.ec, summary, res.reference_m):
                self._pubs[topic].publish(msg)
            self.get_logger().info(
                f"{velocity_text(summary)}, energy-map correlation "
                f"{summary['energy_map_correlation']:.3f}, {summary['lost_units']} lost units "
                f"({summary['frames']} frames)")
            out = self._params.config.out_dir
            if out:
                try:
                    rrd = run.write_run_files(Path(out), res.scene, res.polygons, res.poses,
                                              res.ec)
                    summary["rrd"] = str(rrd)
                    run.write_summary(Path(out), summary)
                    self.get_logger().info(f"wrote {out} (open with: rerun {rrd})")
                except OSError as e:
                    self.get_logger().error(f"cannot write {out}: {e}")
        finally:
            self._busy.release()

    def _refuse(self, reason: str) -> None:
        """Publish the error status with the one-line reason."""
        line = reason.splitlines()[0] if reason else "comparison failed"
        self.get_logger().warning(f"no comparison: {line}")
        if self._closing:
            return
        self._pubs[T.DIAGNOSTICS.name].publish(
            convert.error_diagnostics(self.get_clock().now().nanoseconds, line))

    def close(self) -> None:
        self._closing = True
        w = self._worker
        if w is not None and w.is_alive():
            w.join(timeout=2.0)
            if w.is_alive():
                self.get_logger().warning("stopped while a comparison was running: abandoned")


def main(args=None) -> int:
    """Console entry point (`metarig-compare`)."""
    return run_node(CompareNode, args=args)


if __name__ == "__main__":
    raise SystemExit(main())
