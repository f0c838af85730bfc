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
Simulated source: like a high-speed camera with on-board memory. While capturing it keeps the
measured shaker and stage motion (their joint states); at stop the specimen is solved under
that motion, frames are rendered at `fps` for the capture window (frame k exposed for half a
period up to k / fps) and published stamped at the middle of their exposure (as fast as the
readers acknowledge them, or `rate_factor` x real time).
Lab camera (parameter `hardware` "lab" with `lab_file`, read at start-up; `source` is ignored
unless the file's [camera] is `driver = "sim"`): the camera is opened and its identity checked
when the node starts (`ros_nodes.hardware`; a failure is one logged line, an "error" status and
refused services). `~/start` checks the requested settings (the file's, with the node's
`frame_rate_hz`, `exposure_s`, `pixel_format`, `trigger` overrides) against the file's limits
before the device is configured, then streams from a grab thread (`ros_nodes.logic.camera_stream`):
frames stamped with the camera clock mapped to ROS time where the camera sends time stamps (else
the host receive time; `~/status` "stamps" says which), frames lost counted from the camera's
frame counter (`~/status` "lost", "received"), a camera silent for `grab_timeout_s` ends the
stream in "error" with one line. `~/stop` ends the stream ("done"); `~/snapshot` takes the next
streamed frame, or grabs one (software trigger or free run) when not streaming.
"""

import dataclasses
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
from ros_nodes.hardware import camera_device, camera_settings, lab_camera
from ros_nodes.logic.camera_stream import CameraStream, FrameStamper, one_line
from ros_nodes.logic.cdr import ImageEncoder, restamp
from ros_nodes.nodes._common import CLOCK, COMMAND, LATCHED, STREAM, qos_profile, run_node
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
            self.create_subscription(JointState, T.SHAKER_JOINTS.name, self._on_shaker,
                                     qos_profile(T.SHAKER_JOINTS.qos))
            self._stage_sub = self.create_subscription(JointState, T.STAGE_JOINTS.name,
                                                       self._on_stage,
                                                       qos_profile(T.STAGE_JOINTS.qos))
            threading.Thread(target=self._build_specimen, daemon=True).start()
        self._status("idle", "ready")

    # helpers ---------------------------------------------------------------------------------
    def _status(self, state: str, message: str = "", **extra) -> None:
        self._state = state
        self._status_pub.publish(String(data=json.dumps(
            {"state": state, "frames": self._published, "message": message, **extra})))

    def _build_specimen(self) -> None:
        from hardware_sim.specimen import SpecimenConfig, build

        cfg = self._params.config
        try:
            self._specimen = build(SpecimenConfig(scene=cfg.scene, nx=cfg.nx, ny=cfg.ny,
                                                  design_path=cfg.design_path,
                                                  material_path=cfg.material_path,
                                                  perturb=cfg.perturb, seed=cfg.seed,
                                                  imperfections=cfg.specimen))
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
            self.get_logger().info(
                "device records: " + ", ".join(
                    f"{name} {len(rec)} samples {min(rec)[0]:.4f}-{max(rec)[0]:.4f} s" if rec
                    else f"{name} none" for name, rec in (("shaker", list(self._shaker)),
                                                          ("stage", list(self._stage)))))
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
                                origin_px=centred_origin(self._specimen.nominal_polygons_m,
                                                         cfg.width, cfg.height, cfg.m_per_px),
                                exposure_samples=cfg.exposure_samples, noise_std=cfg.noise_std,
                                lighting_gradient=cfg.lighting_gradient, seed=cfg.seed)

    # lab camera -------------------------------------------------------------------------------
    def _open_lab(self) -> None:
        """Open the lab file's camera; a "sim" entry leaves the node to its `source`."""
        cfg = self._params.config
        try:
            self._section = lab_camera(cfg)
            if self._section is None:
                self._lab = False
                return
            self._camera = camera_device(self._section)
        except Exception as e:  # noqa: BLE001 - lab file, driver and vendor errors: one line
            self._lab_error = f"cannot open the lab camera: {one_line(e)}"
            self.get_logger().error(self._lab_error)
            return
        self.get_logger().info(f"lab camera: {self._camera.identity}")
        try:
            camera_settings(cfg, self._section)
        except ValueError as e:
            self.get_logger().warning(f"the requested camera settings are refused: {e}")

    def _lab_status(self, state: str, message: str) -> None:
        extra = {"camera": self._camera.identity if self._camera is not None else ""}
        if self._stream is not None:
            counts = self._stream.counts()
            counts.pop("frames")
            extra.update(counts, settings=dataclasses.asdict(self._stream.settings))
        with self._lab_lock:
            self._status(state, message, **extra)

    def _lab_tick(self) -> None:
        with self._lab_lock:  # never a "streaming" after the grab thread's "error"
            if self._stream is not None and self._stream.running and not self._stream.error:
                self._lab_status("streaming", f"{self._published} frames")

    def _host_to_ros(self, host_ns: int) -> int:
        """Host clock (ns) -> this node's ROS time: the same clock unless simulated time runs."""
        clock = self.get_clock()
        if not clock.ros_time_is_active:
            return host_ns
        return host_ns + clock.now().nanoseconds - time.time_ns()

    def _lab_configure(self):
        """The requested settings, checked against the lab limits (ValueError before the device
        is touched), then set on the device; returns what the device set."""
        settings = camera_settings(self._params.config, self._section)
        if self._stream is not None and not self._stream.running:
            self._stream.stop()  # a stream that ended by itself: the camera stops acquiring
        try:
            return self._camera.configure(settings)
        except Exception as e:  # noqa: BLE001 - the device's own refusal, vendor exceptions
            raise RuntimeError(f"{self._camera.identity} refused the settings: {one_line(e)}") \
                from None

    def _lab_refuse(self, res, why: str):
        res.success, res.message = False, f"refused: {why}"
        self.get_logger().warning(res.message)
        return res

    def _lab_start(self, res):
        cfg = self._params.config
        if self._camera is None:
            return self._lab_refuse(res, self._lab_error)
        if self._stream is not None and self._stream.running:
            return self._lab_refuse(res, f"camera busy ({self._state})")
        try:
            settings = self._lab_configure()
        except (ValueError, RuntimeError) as e:
            return self._lab_refuse(res, str(e))
        self._published = 0
        self._stream = CameraStream(self._camera, settings, self._publish, cfg.grab_timeout_s,
                                    to_time_ns=self._host_to_ros, on_end=self._lab_failed)
        try:
            self._stream.start()
        except Exception as e:  # noqa: BLE001 - a camera that will not start: one line
            return self._lab_refuse(res, f"{self._camera.identity} did not start: {one_line(e)}")
        roi = "x".join(str(v) for v in settings.roi[2:]) if settings.roi else "full sensor"
        self._lab_status("streaming", f"{settings.frame_rate_hz:g} Hz, {roi}, "
                                      f"{settings.pixel_format}, trigger {settings.trigger}")
        res.success, res.message = True, "streaming"
        return res

    def _lab_failed(self, line: str) -> None:
        """The stream ended by itself (grab thread): the camera stopped delivering or failed."""
        self.get_logger().error(line)
        self._lab_status("error", line)

    def _lab_stop(self, res):
        stream = self._stream
        if stream is None:
            res.success, res.message = True, "stopped (was not streaming)"
            return res
        stream.stop()
        lost = stream.counter.lost
        if stream.error:
            self._lab_status("error", stream.error)
        else:
            self._lab_status("done", f"published {self._published} frames, {lost} lost "
                                     "(camera frame counter)")
        res.success, res.message = True, self._state
        return res

    def _on_rig_stop(self, _msg) -> None:
        if self._stream is not None and self._stream.running:
            self.get_logger().info("rig stop: the camera stops streaming")
            self._lab_stop(Trigger.Response())

    def _lab_snapshot(self, res):
        from hardware_sim.camera import average_frames

        if self._camera is None:
            return self._lab_refuse(res, self._lab_error)
        timeout_s = self._params.config.grab_timeout_s
        n = self._params.config.snapshot_frames
        if self._stream is not None and self._stream.running:
            images = []
            for _ in range(n):
                got = self._stream.next_frame(timeout_s)
                if got is None:
                    return self._lab_refuse(res, f"no streamed frame within {timeout_s:g} s")
                ns, image = got
                images.append(image)
        else:
            try:
                if camera_settings(self._params.config, self._section).trigger == "hardware":
                    return self._lab_refuse(res, "a hardware-triggered camera takes its snapshot "
                                                 "from the stream: start it first")
                settings = self._lab_configure()
                self._camera.start()
                frames = []
                try:
                    for _ in range(n):
                        if settings.trigger == "software":
                            self._camera.trigger()
                        frame = self._camera.grab(timeout_s)
                        if frame is None:
                            break
                        frames.append(frame)
                finally:
                    self._camera.stop()
            except (ValueError, RuntimeError) as e:
                return self._lab_refuse(res, str(e))
            except Exception as e:  # noqa: BLE001 - vendor exceptions: one line
                return self._lab_refuse(res, f"{self._camera.identity}: {one_line(e)}")
            if len(frames) < n:
                return self._lab_refuse(res, f"{self._camera.identity} gave no frame within "
                                             f"{timeout_s:g} s")
            ns = self._host_to_ros(FrameStamper().stamp(frames[-1]))
            images = [f.image for f in frames]
        image = average_frames(images)
        enc = ImageEncoder(image.shape[0], image.shape[1], image.dtype,
                           self._params.config.frame_id)
        self._reference.publish(enc.encode(ns, image))
        res.success, res.message = True, "reference image published"
        return res

    # services ---------------------------------------------------------------------------------
    def _on_snapshot(self, req, res):
        if self._lab:
            return self._lab_snapshot(res)
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
            frame = reference_frame(self._specimen, self._camera_config(), cfg.seed,
                                    cfg.snapshot_frames)
            self._reference.publish(self._enc_for(frame).encode(
                self.get_clock().now().nanoseconds, frame))
            res.success, res.message = True, "reference image published"
        return res

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
