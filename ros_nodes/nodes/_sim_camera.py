"""The camera node's simulated-camera path (`CameraNode` with `source` "sim").

Like a high-speed camera with on-board memory. While capturing it keeps the measured shaker and
stage motion (their joint states); at stop the specimen is solved under that motion, frames are
rendered at `fps` for the capture window (frame k exposed for half a period up to k / fps) and
published stamped at the middle of their exposure (as fast as the readers acknowledge them, or
`rate_factor` x real time), each with the true unit poses on `/camera/ground_truth`. Its
snapshot is the unloaded specimen at rest, refused once the stages have moved.

A mixin of `CameraNode` (it adds methods, overrides none): the node owns the publishers, the
status and the frame publishing it uses.
"""

import hashlib
import time

import numpy as np
from rclpy.duration import Duration
from sensor_msgs.msg import JointState
from std_msgs.msg import String

from ros_nodes import convert


class SimCameraPath:
    """Methods of `CameraNode` for the simulated camera (see the module docstring)."""

    def _build_specimen(self) -> None:
        from hardware_sim.specimen import SpecimenConfig, build

        cfg = self._params.config
        try:
            self._specimen = build(
                SpecimenConfig(
                    scene=cfg.scene,
                    nx=cfg.nx,
                    ny=cfg.ny,
                    design_path=cfg.design_path,
                    material_path=cfg.material_path,
                    material_si=cfg.material_si,
                    perturb=cfg.perturb,
                    seed=cfg.seed,
                    imperfections=cfg.specimen,
                )
            )
            self._design.publish(String(data=self._specimen.design_json()))
        except Exception as e:  # noqa: BLE001 - reported on the status topic, node stays up
            self._status("error", f"cannot build the specimen: {e}")

    def _on_shaker(self, msg: JointState) -> None:
        t, _, pos, _ = convert.joint_state_arrays(msg)
        self._shaker.append((t * 1e-9, float(pos[0])))

    def _on_stage(self, msg: JointState) -> None:
        t, _, pos, _ = convert.joint_state_arrays(msg)
        self._stage.append((t * 1e-9, float(pos.sum())))

    def _await_device_records(self, t1: float, timeout_s: float = 5.0) -> None:
        """Wait until the shaker's (and the stages') joint states hold every sample up to the
        end of the capture `t1` (s; `hardware_sim.rig.record_complete`): the last messages may
        still be in flight when the capture stops, and a record that ends early would be held at
        its last value for the remaining frames."""
        from hardware_sim.rig import record_complete

        def short():
            return [
                name
                for name, rec in (("shaker", self._shaker), ("stage", self._stage))
                if rec and not record_complete([s[0] for s in list(rec)], t1)
            ]

        deadline = time.monotonic() + timeout_s
        while short() and time.monotonic() < deadline:
            time.sleep(0.01)
        for name in short():
            self.get_logger().warning(
                f"the {name} joint states end before the capture ({t1:.4f} s): held at their "
                "last value for the last frames"
            )

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
            # what the specimen is solved under, and the samples left out (after the capture;
            # how many depends on the load): in two runs of one seed, the first part is the same
            counts = [
                (name, [s[0] for s in list(rec)])
                for name, rec in (("shaker", self._shaker), ("stage", self._stage))
            ]
            digest = hashlib.sha256(
                b"".join(
                    np.ascontiguousarray(a).tobytes()
                    for r in (shaker, stage)
                    for a in (r.t, r.value)
                )
            ).hexdigest()[:16]
            self.get_logger().info(
                f"device records up to {t1:.4f} s (sha256 {digest}): "
                + ", ".join(
                    f"{name} {sum(t <= t1 for t in ts)} samples"
                    f" ({sum(t > t1 for t in ts)} later ones left out)"
                    for name, ts in counts
                )
            )
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
        return cam.CameraConfig(
            width_px=cfg.width,
            height_px=cfg.height,
            fps=cfg.fps,
            m_per_px=cfg.m_per_px,
            supersample=cfg.supersample,
            origin_px=centred_origin(
                self._specimen.nominal_polygons_m, cfg.width, cfg.height, cfg.m_per_px
            ),
            exposure_samples=cfg.exposure_samples,
            noise_std=cfg.noise_std,
            lighting_gradient=cfg.lighting_gradient,
            seed=cfg.seed,
        )

    def _sim_snapshot(self, res):
        from hardware_sim.rig import reference_frame

        cfg = self._params.config
        if cfg.source != "sim":
            res.success, res.message = False, f"refused: no snapshot from a {cfg.source} source"
        elif self._specimen is None:
            res.success, res.message = False, "refused: the specimen is not built yet"
        elif self._state == "capturing" or any(abs(v) > 1e-9 for _, v in list(self._stage)):
            res.success, res.message = (
                False,
                (
                    "refused: the simulated camera can only take the "
                    "unloaded specimen (before the stages move)"
                ),
            )
        else:
            frame = reference_frame(
                self._specimen, self._camera_config(), cfg.seed, cfg.snapshot_frames
            )
            self._reference.publish(
                self._enc_for(frame).encode(self.get_clock().now().nanoseconds, frame)
            )
            res.success, res.message = True, "reference image published"
        return res
