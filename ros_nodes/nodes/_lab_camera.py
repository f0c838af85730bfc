"""The camera node's lab-camera path (`CameraNode` with `hardware` "lab").

Parameter `hardware` "lab" with `lab_file`, read at start-up; `source` is ignored unless the
file's [camera] is `driver = "sim"`: the camera is opened and its identity checked when the node
starts (`ros_nodes.hardware`; a failure is one logged line, an "error" status and refused
services). `~/start` checks the requested settings (the file's, with the node's
`frame_rate_hz`, `exposure_s`, `pixel_format`, `trigger` overrides) against the file's limits
before the device is configured, then streams from a grab thread
(`ros_nodes.logic.camera_stream`): frames stamped with the camera clock mapped to ROS time where
the camera sends time stamps (else the host receive time; `~/status` "stamps" says which),
frames lost counted from the camera's frame counter (`~/status` "lost", "received"), a camera
silent for `grab_timeout_s` ends the stream in "error" with one line. `~/stop` and `/rig/stop`
end the stream ("done"); `~/snapshot` averages the next `snapshot_frames` streamed frames, or
grabs them (software trigger or free run) when not streaming.

A mixin of `CameraNode` (it adds methods, overrides none): the node owns the publishers, the
status and the frame publishing it uses.
"""

import dataclasses
import time

from std_srvs.srv import Trigger

from ros_nodes.hardware import camera_device, camera_settings, lab_camera
from ros_nodes.logic.camera_stream import CameraStream, FrameStamper, one_line
from ros_nodes.logic.cdr import ImageEncoder


class LabCameraPath:
    """Methods of `CameraNode` for a lab camera (see the module docstring)."""

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
            raise RuntimeError(
                f"{self._camera.identity} refused the settings: {one_line(e)}"
            ) from None

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
        self._stream = CameraStream(
            self._camera,
            settings,
            self._publish,
            cfg.grab_timeout_s,
            to_time_ns=self._host_to_ros,
            on_end=self._lab_failed,
        )
        try:
            self._stream.start()
        except Exception as e:  # noqa: BLE001 - a camera that will not start: one line
            return self._lab_refuse(res, f"{self._camera.identity} did not start: {one_line(e)}")
        roi = "x".join(str(v) for v in settings.roi[2:]) if settings.roi else "full sensor"
        self._lab_status(
            "streaming",
            f"{settings.frame_rate_hz:g} Hz, {roi}, "
            f"{settings.pixel_format}, trigger {settings.trigger}",
        )
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
            self._lab_status(
                "done", f"published {self._published} frames, {lost} lost (camera frame counter)"
            )
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
                    return self._lab_refuse(
                        res,
                        "a hardware-triggered camera takes its snapshot "
                        "from the stream: start it first",
                    )
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
                return self._lab_refuse(
                    res, f"{self._camera.identity} gave no frame within {timeout_s:g} s"
                )
            ns = self._host_to_ros(FrameStamper().stamp(frames[-1]))
            images = [f.image for f in frames]
        image = average_frames(images)
        enc = ImageEncoder(
            image.shape[0], image.shape[1], image.dtype, self._params.config.frame_id
        )
        self._reference.publish(enc.encode(ns, image))
        res.success, res.message = True, "reference image published"
        return res
