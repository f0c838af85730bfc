"""Camera source node: frames from the simulated rig or from a recording (MCAP, images, video).

Interfaces (node name `camera`):
- services `~/start` / `~/stop` (std_srvs/Trigger): replay sources stream from start; the
  simulated camera captures between start and stop and then downloads the footage (see below).
- service `~/snapshot` (std_srvs/Trigger): one frame now on `/camera/reference_image` (latched),
  the tracker's reference; the sequencer takes it before the stages close (simulated: the
  specimen at rest, refused once the stages have moved).
- `/camera/image_raw` (sensor_msgs/Image mono8/mono16) + `/camera/camera_info`, same stamps;
  `/camera/ground_truth` (metarig_msgs/UnitPose2DArray, simulated only: true unit poses in the
  sample frame at each frame time); `/rig/design` (std_msgs/String JSON, latched, simulated);
  `~/status` (std_msgs/String JSON, latched): state, frames published, message;
  `/clock` when `publish_clock` (replay: the frame stamps drive simulated time).
Simulated source: like a high-speed camera with on-board memory. While capturing it keeps the
measured shaker and stage motion (their joint states); at stop the specimen is solved under
that motion, frames are rendered at `fps` for the capture window (frame k exposed for half a
period up to k / fps) and published stamped at the middle of their exposure (as fast as the
readers acknowledge them, or `rate_factor` x real time).
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
from std_msgs.msg import String
from std_srvs.srv import Trigger

from ros_nodes import convert
from ros_nodes import topics as T
from ros_nodes.logic.cdr import ImageEncoder, restamp
from ros_nodes.nodes._common import CLOCK, LATCHED, STREAM, run_node
from ros_nodes.nodes._params import TypedParams
from ros_nodes.params import CameraNodeConfig
from tracking.frame_sources import SourceError, open_replay

NAME = "camera"
ACK_EVERY = 20  # frames between flow-control waits when publishing as fast as possible


class CameraNode(Node):
    """Thin adapter over `tracking.frame_sources` (replay) and `hardware_sim.rig` (simulated)."""

    def __init__(self, **kwargs):
        super().__init__(NAME, **kwargs)
        self._params = TypedParams(self, CameraNodeConfig)
        cfg = self._params.config
        frames_qos = QoSProfile(depth=cfg.queue_depth, reliability=STREAM.reliability,
                                history=STREAM.history)
        self._img = self.create_publisher(Image, T.IMAGE.name, frames_qos)
        self._info = self.create_publisher(CameraInfo, T.CAMERA_INFO.name, STREAM)
        self._status_pub = self.create_publisher(String, T.CAMERA_STATUS.name, LATCHED)
        self._clock_pub = self.create_publisher(Clock, T.CLOCK.name, CLOCK) if cfg.publish_clock else None
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
        if cfg.source == "sim":
            self._truth = self.create_publisher(UnitPose2DArray, T.GROUND_TRUTH.name, STREAM)
            self._design = self.create_publisher(String, T.RIG_DESIGN.name, LATCHED)
            self.create_subscription(JointState, T.SHAKER_JOINTS.name, self._on_shaker, STREAM)
            self._stage_sub = self.create_subscription(JointState, T.STAGE_JOINTS.name,
                                                       self._on_stage, STREAM)
            threading.Thread(target=self._build_specimen, daemon=True).start()
        self._status("idle", "ready")

    # helpers ---------------------------------------------------------------------------------
    def _status(self, state: str, message: str = "") -> None:
        self._state = state
        self._status_pub.publish(String(data=json.dumps(
            {"state": state, "frames": self._published, "message": message})))

    def _build_specimen(self) -> None:
        from hardware_sim.specimen import SpecimenConfig, build

        cfg = self._params.config
        try:
            self._specimen = build(SpecimenConfig(scene=cfg.scene, nx=cfg.nx, ny=cfg.ny,
                                                  design_path=cfg.design_path,
                                                  material_path=cfg.material_path,
                                                  perturb=cfg.perturb, seed=cfg.seed))
            self._design.publish(String(data=self._specimen.design_json()))
        except Exception as e:  # noqa: BLE001 - reported on the status topic, node stays up
            self._status("error", f"cannot build the specimen: {e}")

    def _publish(self, ns: int, frame: np.ndarray) -> None:
        # hot path (1000 frames/s): publish serialized bytes built without message objects;
        # the encoder and the camera info are made once per frame shape
        enc = self._enc_for(frame)
        if self._clock_pub is not None:
            self._clock_pub.publish(convert.clock(ns))
        self._img.publish(enc.encode(ns, frame))
        self._info.publish(restamp(self._info_cdr, ns))
        self._published += 1

    def _enc_for(self, frame: np.ndarray) -> ImageEncoder:
        """The encoder (and camera info) for this frame shape, made once per shape."""
        key = (frame.shape, frame.dtype)
        if key != self._enc_key:
            cfg = self._params.config
            if frame.ndim != 2:
                raise ValueError(f"frames must be 2-D, got {frame.shape}")
            self._enc = ImageEncoder(frame.shape[0], frame.shape[1], frame.dtype, cfg.frame_id)
            self._info_cdr = serialize_message(convert.camera_info(
                0, frame.shape[1], frame.shape[0], cfg.m_per_px, cfg.frame_id))
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
        try:
            frames = open_replay(cfg.source, cfg.path, cfg.fps, cfg.width, cfg.height,
                                 cfg.n_frames, cfg.image_topic, cfg.seed)
            base = self.get_clock().now().nanoseconds if not cfg.publish_clock else 0
            while True:
                wall0 = time.perf_counter()
                for k, (t_rel, frame) in enumerate(frames):
                    if self._stop_evt.is_set() or (cfg.n_frames and self._published >= cfg.n_frames):
                        break
                    self._pace(k, t_rel, wall0)
                    self._publish(base + t_rel, frame)
                if not cfg.loop or self._stop_evt.is_set() or cfg.n_frames and \
                        self._published >= cfg.n_frames:
                    break
                frames = open_replay(cfg.source, cfg.path, cfg.fps, cfg.width, cfg.height,
                                     cfg.n_frames, cfg.image_topic, cfg.seed)
                base += t_rel + int(1e9 / cfg.fps)
            self._status("done", f"published {self._published} frames")
        except SourceError as e:
            self.get_logger().error(str(e))
            self._status("error", str(e))

    # simulated camera -------------------------------------------------------------------------
    def _on_shaker(self, msg: JointState) -> None:
        t, _, pos, _ = convert.joint_state_arrays(msg)
        self._shaker.append((t * 1e-9, float(pos[0])))

    def _on_stage(self, msg: JointState) -> None:
        t, _, pos, _ = convert.joint_state_arrays(msg)
        self._stage.append((t * 1e-9, float(pos.sum())))

    def _await_device_records(self, t1: float, timeout_s: float = 2.0) -> None:
        """Wait until the shaker's (and the stages') joint states reach the end of the capture
        `t1` (s): the last messages may still be in flight when the capture stops, and a record
        that ends early would be held at its last value for the remaining frames."""
        def short():
            out = []
            for name, rec in (("shaker", self._shaker), ("stage", self._stage)):
                t = np.sort([s[0] for s in list(rec)])
                # a device samples at its own rate: its last sample may be up to one period
                # before the end of the capture
                period = float(np.median(np.diff(t[-20:]))) if t.size > 1 else 0.0
                if t.size and t[-1] < t1 - period - 1e-9:
                    out.append(name)
            return out

        deadline = time.monotonic() + timeout_s
        while short() and time.monotonic() < deadline:
            time.sleep(0.01)
        for name in short():
            self.get_logger().warning(
                f"the {name} joint states end before the capture ({t1:.4f} s): held at their "
                "last value for the last frames")

    def _capture_end(self, settle_s: float = 0.05, timeout_s: float = 2.0) -> float:
        """The time the capture ended, s: now on a wall clock; on simulated time, the time the
        clock holds once it has stopped moving (the sequencer holds it before it stops the
        camera). Read in the service callback, a /clock message already sent but not yet
        handled by this node would end the capture a step early and drop the last frame."""
        clock = self.get_clock()
        now = clock.now().nanoseconds
        if not clock.ros_time_is_active:
            return now * 1e-9
        still = time.monotonic()
        deadline = still + timeout_s
        while time.monotonic() < deadline:
            time.sleep(0.005)
            t = clock.now().nanoseconds
            if t != now:
                now, still = t, time.monotonic()
            elif time.monotonic() - still >= settle_s:
                break
        return now * 1e-9

    def _develop(self) -> None:
        from hardware_sim.rig import MotionRecord, capture_times, exposure_motion, film

        cfg = self._params.config
        try:
            while self._specimen is None and self._state != "error":
                time.sleep(0.05)  # the specimen is still being built (first JAX import)
            if self._specimen is None:
                return
            self._window[1] = self._capture_end()
            t0, t1 = self._window
            times = capture_times(t0, t1, cfg.fps)
            if times.size < 1:
                raise ValueError(f"capture window [{t0:.4f}, {t1:.4f}] s holds no frame")
            self._status("developing", f"solving the specimen for {times.size} frames")
            self._await_device_records(t1)
            shaker = MotionRecord.from_samples(list(self._shaker), t1)
            stage = MotionRecord.from_samples(list(self._stage), t1)
            traj = exposure_motion(self._specimen, times, shaker, stage, cfg.fps)
            ccfg = self._camera_config()
            c0 = self._specimen.centroids_m()
            self._status("publishing", f"{times.size} frames")
            wall0 = time.perf_counter()
            rng = np.random.default_rng(cfg.seed)
            for k, (t, frame, q) in enumerate(film(self._specimen, ccfg, traj, rng)):
                if self._stop_evt.is_set():
                    break
                ns = int(round(t * 1e9))
                self._pace(k, int(round((t - float(traj.t[1])) * 1e9)), wall0)
                self._truth.publish(convert.unit_poses(ns, q, c0))
                self._publish(ns, frame)
            self._img.wait_for_all_acked(Duration(seconds=5.0))
            self._status("done", f"published {self._published} frames")
        except Exception as e:  # noqa: BLE001 - reported on the status topic, node stays up
            self.get_logger().error(f"simulated camera failed: {e}")
            self._status("error", str(e))

    def _camera_config(self):
        from hardware_sim import camera as cam
        from hardware_sim.rig import centred_origin

        cfg = self._params.config
        return cam.CameraConfig(width_px=cfg.width, height_px=cfg.height, fps=cfg.fps,
                                m_per_px=cfg.m_per_px, supersample=cfg.supersample,
                                origin_px=centred_origin(self._specimen.polygons_m, cfg.width,
                                                         cfg.height, cfg.m_per_px),
                                exposure_samples=cfg.exposure_samples, noise_std=cfg.noise_std,
                                lighting_gradient=cfg.lighting_gradient, seed=cfg.seed)

    # services ---------------------------------------------------------------------------------
    def _on_snapshot(self, req, res):
        from hardware_sim.rig import reference_frame

        cfg = self._params.config
        if cfg.source != "sim":
            res.success, res.message = False, f"refused: no snapshot from a {cfg.source} source"
        elif self._specimen is None:
            res.success, res.message = False, "refused: the specimen is not built yet"
        elif self._state == "capturing" or any(abs(v) > 1e-9 for _, v in list(self._stage)):
            res.success, res.message = False, ("refused: the simulated camera can only take the "
                                               "unloaded specimen (before the stages move)")
        else:
            frame = reference_frame(self._specimen, self._camera_config(), cfg.seed)
            self._reference.publish(self._enc_for(frame).encode(
                self.get_clock().now().nanoseconds, frame))
            res.success, res.message = True, "reference image published"
        return res

    def _on_start(self, req, res):
        cfg = self._params.config
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


def main(args=None) -> int:
    return run_node(CameraNode, args=args)


if __name__ == "__main__":
    raise SystemExit(main())
