"""Camera source node: frames from the simulated rig, a recording (MCAP, images, video) or a lab
camera (pylon or GenICam, through the camera port).

Interfaces (node name `camera`):
- services `~/start` / `~/stop` (std_srvs/Trigger): replay sources stream from start; the
  simulated camera captures between start and stop and then downloads the footage (see below).
- topic `/rig/stop` (std_msgs/Empty): a lab camera's stream stops (as `~/stop`).
- service `~/snapshot` (std_srvs/Trigger): the mean of the next `snapshot_frames` frames (default
  8: the reference's read noise is in every tracked pose) on `/camera/reference_image` (latched),
  the tracker's reference; the sequencer takes it before the stages close (simulated: the
  specimen at rest, refused once the stages have moved).
- `/camera/image_raw` (sensor_msgs/Image mono8/mono16) + `/camera/camera_info`, same stamps;
  `/camera/ground_truth` (metarig_msgs/UnitPose2DArray, simulated only: true unit poses in the
  sample frame at each frame time); `/rig/design` (std_msgs/String JSON, latched, simulated);
  `~/status` (std_msgs/String JSON, latched): state, frames published, message;
  `/clock` when `publish_clock` (replay: the frame stamps drive simulated time).
The simulated camera's path is `ros_nodes.nodes._sim_camera`, a lab camera's
`ros_nodes.nodes._lab_camera`; this module holds the node, the replay sources and the services.
"""

import json
import threading
import time

import numpy as np
from metarig_msgs.msg import UnitPose2DArray
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile
from rclpy.serialization import serialize_message
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import CameraInfo, Image, JointState
from std_msgs.msg import Empty, String
from std_srvs.srv import Trigger

from ros_nodes import convert
from ros_nodes import topics as T
from ros_nodes.logic.camera_stream import CameraStream, one_line
from ros_nodes.logic.cdr import ImageEncoder, restamp
from ros_nodes.nodes._common import CLOCK, COMMAND, LATCHED, STREAM, qos_profile, run_node
from ros_nodes.nodes._lab_camera import LabCameraPath
from ros_nodes.nodes._params import TypedParams
from ros_nodes.nodes._sim_camera import SimCameraPath
from ros_nodes.params import CameraNodeConfig
from tracking.frame_sources import SourceError, open_replay

NAME = "camera"
ACK_EVERY = 20  # frames between flow-control waits when publishing as fast as possible


class CameraNode(LabCameraPath, SimCameraPath, Node):
    """Thin adapter over `tracking.frame_sources` (replay), `hardware_sim.rig` (simulated,
    `SimCameraPath`) and the camera port (lab, `LabCameraPath`)."""

    def __init__(self, **kwargs):
        super().__init__(NAME, **kwargs)
        self._params = TypedParams(self, CameraNodeConfig)
        cfg = self._params.config
        frames_qos = QoSProfile(
            depth=cfg.queue_depth, reliability=STREAM.reliability, history=STREAM.history
        )
        self._img = self.create_publisher(Image, T.IMAGE.name, frames_qos)
        self._info = self.create_publisher(CameraInfo, T.CAMERA_INFO.name, STREAM)
        self._status_pub = self.create_publisher(String, T.CAMERA_STATUS.name, LATCHED)
        self._clock_pub = (
            self.create_publisher(Clock, T.CLOCK.name, CLOCK) if cfg.publish_clock else None
        )
        self.create_service(Trigger, T.CAMERA_START.name, self._on_start)
        self.create_service(Trigger, T.CAMERA_STOP.name, self._on_stop)
        self.create_service(Trigger, T.CAMERA_SNAPSHOT.name, self._on_snapshot)
        self._reference = self.create_publisher(Image, T.REFERENCE_IMAGE.name, LATCHED)
        self._stop_evt = threading.Event()
        self._thread: threading.Thread | None = None
        self._published = 0
        self._window = [None, None]
        self._shaker: list[tuple[float, float]] = []
        self._stage: list[tuple[float, float]] = []
        self._specimen = None
        self._enc_key = None
        self._enc: ImageEncoder | None = None
        self._info_cdr = b""
        # the lab camera (hardware "lab" naming a real camera): see the module docstring
        self._lab = cfg.hardware == "lab"
        self._section = None
        self._camera = None
        self._stream: CameraStream | None = None
        self._lab_error = ""
        self._lab_lock = threading.RLock()  # the grab thread's error vs the status timer
        if self._lab:
            self._open_lab()
        if self._lab:
            self.create_timer(0.5, self._lab_tick)
            self.create_subscription(Empty, T.RIG_STOP.name, self._on_rig_stop, COMMAND)
            if self._camera is None:
                self._status("error", self._lab_error)
            else:
                self._lab_status("idle", f"ready: {self._camera.identity}")
            return
        if cfg.source == "sim":
            self._truth = self.create_publisher(UnitPose2DArray, T.GROUND_TRUTH.name, STREAM)
            self._design = self.create_publisher(String, T.RIG_DESIGN.name, LATCHED)
            self.create_subscription(
                JointState, T.SHAKER_JOINTS.name, self._on_shaker, qos_profile(T.SHAKER_JOINTS.qos)
            )
            self._stage_sub = self.create_subscription(
                JointState, T.STAGE_JOINTS.name, self._on_stage, qos_profile(T.STAGE_JOINTS.qos)
            )
            threading.Thread(target=self._build_specimen, daemon=True).start()
        self._status("idle", "ready")

    # helpers ---------------------------------------------------------------------------------
    def _status(self, state: str, message: str = "", **extra) -> None:
        self._state = state
        self._status_pub.publish(
            String(
                data=json.dumps(
                    {"state": state, "frames": self._published, "message": message, **extra}
                )
            )
        )

    def _publish(self, ns: int, frame: np.ndarray) -> None:
        # hot path (1000 frames/s): publish serialized bytes built without message objects;
        # the encoder and the camera info are made once per frame shape
        enc = self._enc_for(frame)
        if self._clock_pub is not None:
            self._clock_pub.publish(convert.clock(ns))
        self._img.publish(enc.encode(ns, frame))
        self._info.publish(restamp(self._info_cdr, ns))
        self._published += 1
        if self._lab and self._published == 1:  # the sequencer fires the pulse on this
            self._lab_status("streaming", "first frame")

    def _enc_for(self, frame: np.ndarray) -> ImageEncoder:
        """The encoder (and camera info) for this frame shape, made once per shape."""
        key = (frame.shape, frame.dtype)
        if key != self._enc_key:
            cfg = self._params.config
            if frame.ndim != 2:
                raise ValueError(f"frames must be 2-D, got {frame.shape}")
            self._enc = ImageEncoder(frame.shape[0], frame.shape[1], frame.dtype, cfg.frame_id)
            self._info_cdr = serialize_message(
                convert.camera_info(0, frame.shape[1], frame.shape[0], cfg.m_per_px, cfg.frame_id)
            )
            self._enc_key = key
        return self._enc

    def _pace(self, k: int, t_rel_ns: int, wall0: float) -> None:
        cfg = self._params.config
        if cfg.rate_factor > 0:
            delay = wall0 + t_rel_ns * 1e-9 / cfg.rate_factor - time.perf_counter()
            if delay > 0:
                self._stop_evt.wait(delay)
        elif k % ACK_EVERY == ACK_EVERY - 1:
            self._img.wait_for_all_acked(Duration(seconds=2.0))

    # replay -----------------------------------------------------------------------------------
    def _replay(self) -> None:
        cfg = self._params.config

        def replay():
            return open_replay(
                cfg.source,
                cfg.path,
                cfg.fps,
                cfg.width,
                cfg.height,
                cfg.n_frames,
                cfg.image_topic,
                cfg.seed,
            )

        try:
            frames = replay()
            base = self.get_clock().now().nanoseconds if not cfg.publish_clock else 0
            while True:
                wall0 = time.perf_counter()
                for k, (t_rel, frame) in enumerate(frames):
                    if self._stop_evt.is_set() or (
                        cfg.n_frames and self._published >= cfg.n_frames
                    ):
                        break
                    self._pace(k, t_rel, wall0)
                    self._publish(base + t_rel, frame)
                if (
                    not cfg.loop
                    or self._stop_evt.is_set()
                    or cfg.n_frames
                    and self._published >= cfg.n_frames
                ):
                    break
                frames = replay()
                base += t_rel + int(1e9 / cfg.fps)
            self._status("done", f"published {self._published} frames")
        except SourceError as e:
            self.get_logger().error(str(e))
            self._status("error", str(e))

    # services ---------------------------------------------------------------------------------
    def _on_snapshot(self, req, res):
        return self._lab_snapshot(res) if self._lab else self._sim_snapshot(res)

    def _on_start(self, req, res):
        cfg = self._params.config
        if self._lab:
            return self._lab_start(res)
        if self._thread is not None and self._thread.is_alive() or self._state == "capturing":
            res.success, res.message = False, f"refused: camera busy ({self._state})"
            return res
        self._stop_evt.clear()
        self._published = 0
        if cfg.source == "sim":
            t0 = self.get_clock().now().nanoseconds * 1e-9
            if cfg.capture_start_s >= 0.0:  # set by the sequencer: the time it holds
                t0 = cfg.capture_start_s
                self.set_parameters([Parameter("capture_start_s", value=-1.0)])
            self._window = [t0, None]
            self._status("capturing", f"from t={self._window[0]:.4f} s")
        else:
            self._thread = threading.Thread(target=self._replay, daemon=True)
            self._status("streaming", cfg.source)
            self._thread.start()
        res.success, res.message = True, self._state
        return res

    def _on_stop(self, req, res):
        cfg = self._params.config
        if self._lab:
            return self._lab_stop(res)
        if cfg.source == "sim" and self._state == "capturing":
            self._window[1] = None  # set by `_develop` once the clock has settled
            self._thread = threading.Thread(target=self._develop, daemon=True)
            self._thread.start()
            res.success, res.message = True, "capture ended; developing the footage"
        else:
            self._stop_evt.set()
            res.success, res.message = True, "stopped"
        return res

    def close(self) -> None:
        self._stop_evt.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        if self._stream is not None:
            self._stream.stop()
        if self._camera is not None:
            try:
                self._camera.close()
            except Exception as e:  # noqa: BLE001 - closing on the way out: say so, go on
                self.get_logger().warning(f"the lab camera did not close: {one_line(e)}")
            self._camera = None


def main(args=None) -> int:
    return run_node(CameraNode, args=args)


if __name__ == "__main__":
    raise SystemExit(main())
