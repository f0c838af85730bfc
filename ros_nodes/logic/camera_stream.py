"""A real camera's stream, without ROS: the grab thread behind the camera node (`hardware: lab`).

- `FrameStamper`: each frame's time, host clock in ns: the camera's own time stamp mapped
  through `ClockMap` where the frame has one, else the host time at which the driver received
  it; `source` says which (for the node's status).
- `CameraStream`: starts a configured camera and grabs on its own thread (never the
  executor's), fires the software trigger at the frame rate where the settings ask for one,
  counts frames lost from the camera's frame counter (`FrameCounter`), hands every frame to
  `publish(stamp_ns, image)`, and ends in an error (one line, `error`) when the camera
  delivers nothing for `timeout_s` while streaming (with a hardware trigger, from the first
  frame on: before it the camera waits for its edges). Frames already handed on stay handed on.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import numpy as np

from devices.camera.port import Camera, CameraSettings, ClockMap, Frame, FrameCounter

CAMERA_CLOCK = "camera clock"
HOST_CLOCK = "host receive time"


def one_line(e: BaseException) -> str:
    """An exception as one line: its first line, or its type when it says nothing."""
    text = str(e).strip()
    return text.splitlines()[0] if text else type(e).__name__


class FrameStamper:
    """Stamps frames on the host clock (ns): through a `ClockMap` of the camera clock where the
    frame carries one, else the host receive time."""

    def __init__(self, window: int = 1000):
        self.clock = ClockMap(window)
        self.camera_stamped = 0
        self.host_stamped = 0

    def stamp(self, frame: Frame) -> int:
        if frame.device_time_s is None:
            self.host_stamped += 1
            return int(frame.host_time_ns)
        self.clock.add(frame.device_time_s, frame.host_time_ns)
        self.camera_stamped += 1
        return self.clock.to_host_ns(frame.device_time_s)

    @property
    def source(self) -> str:
        """Where the stamps came from: the camera clock, the host receive time, or both."""
        if self.camera_stamped and self.host_stamped:
            return (f"{CAMERA_CLOCK} ({self.camera_stamped} frames) and {HOST_CLOCK} "
                    f"({self.host_stamped} frames without a camera time stamp)")
        if self.camera_stamped:
            return f"{CAMERA_CLOCK} (mapped to the host clock, offset {self.clock.offset_ns} ns)"
        return f"{HOST_CLOCK} (the camera sends no time stamps)" if self.host_stamped else ""


class CameraStream:
    """One stream of a configured camera (see the module docstring).

    camera: an open camera, configured with `settings`.
    publish: called on the grab thread with (stamp_ns, image) for every frame, in order.
    timeout_s: no frame for this long while streaming ends the stream in an error.
    to_time_ns: maps the host clock (ns) to the stamps' clock (default: the host clock itself).
    on_end: called on the grab thread when the stream ends by itself (an error), with the line.
    """

    def __init__(self, camera: Camera, settings: CameraSettings,
                 publish: Callable[[int, np.ndarray], None], timeout_s: float = 2.0,
                 poll_s: float = 0.05, to_time_ns: Callable[[int], int] | None = None,
                 on_end: Callable[[str], None] | None = None):
        self.camera, self.settings = camera, settings
        self.publish = publish
        self.timeout_s, self.poll_s = float(timeout_s), float(poll_s)
        self.to_time_ns = to_time_ns or (lambda ns: ns)
        self.on_end = on_end
        self.counter = FrameCounter(*getattr(camera, "counter_bits", (64, 0)))
        self.stamper = FrameStamper()
        self.published = 0
        self.error = ""
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._waiters: list[dict] = []
        self._lock = threading.Lock()

    # -- control ---------------------------------------------------------------------------------
    def start(self) -> None:
        self.camera.start()
        self._thread = threading.Thread(target=self._run, name="camera-grab", daemon=True)
        self._thread.start()

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def stop(self, timeout_s: float = 5.0) -> None:
        """End the stream (the frame being grabbed is still handed on) and stop the camera."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout_s)
        try:
            self.camera.stop()
        except Exception as e:  # noqa: BLE001 - a camera gone away: the stream is over anyway
            if not self.error:
                self.error = f"{self.camera.identity} did not stop: {one_line(e)}"

    def next_frame(self, timeout_s: float) -> tuple[int, np.ndarray] | None:
        """The next frame the stream hands on, (stamp_ns, image); None if none within
        `timeout_s` or the stream ended."""
        slot: dict = {"done": threading.Event()}
        with self._lock:
            self._waiters.append(slot)
        deadline = time.monotonic() + timeout_s
        while not slot["done"].wait(0.05):
            if time.monotonic() > deadline or not self.running:
                with self._lock:
                    if slot in self._waiters:
                        self._waiters.remove(slot)
                break
        return slot.get("frame")

    def counts(self) -> dict:
        """Frames published, and the camera counter's account (received, lost, repeated,
        restarts), with where the stamps came from."""
        return {"frames": self.published, **self.counter.summary(),
                "stamps": self.stamper.source}

    # -- the grab thread -------------------------------------------------------------------------
    def _run(self) -> None:
        s = self.settings
        period = 1.0 / s.frame_rate_hz
        software = s.trigger == "software"
        edges = s.trigger == "hardware"
        last = time.monotonic()
        next_trigger = last
        try:
            while not self._stop.is_set():
                wait = self.poll_s
                if software:
                    now = time.monotonic()
                    if now >= next_trigger:
                        self.camera.trigger()
                        next_trigger = max(next_trigger + period, now)
                    wait = min(wait, max(next_trigger - time.monotonic(), 0.001))
                frame = self.camera.grab(wait)
                now = time.monotonic()
                if frame is None:
                    if now - last > self.timeout_s and not (edges and not self.counter.received):
                        self.error = (f"{self.camera.identity} delivered no frame for more "
                                      f"than {self.timeout_s:g} s (grab_timeout_s): stream "
                                      f"stopped after {self.published} frames")
                        break
                    continue
                last = now
                self.counter.update(frame.counter)
                stamp = self.to_time_ns(self.stamper.stamp(frame))
                self.publish(stamp, frame.image)
                self.published += 1
                with self._lock:
                    waiters, self._waiters = self._waiters, []
                for slot in waiters:
                    slot["frame"] = (stamp, frame.image)
                    slot["done"].set()
        except Exception as e:  # noqa: BLE001 - a driver or publisher failure ends the stream
            self.error = f"{self.camera.identity}: {one_line(e)}"
        if self.error:
            try:                # the camera stops acquiring, so that it can be configured again
                self.camera.stop()
            except Exception:  # noqa: BLE001, S110 - a camera gone away: the error says enough
                pass
            if self.on_end is not None:
                self.on_end(self.error)
