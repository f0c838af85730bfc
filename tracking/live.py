"""Live DIC preview (pure, no ROS): newest-frame slot + a tracking thread at a capped rate.

The camera callback hands frames to `LivePreview.offer`, which only swaps a reference under a
lock and returns: it never waits for tracking, so the camera is never blocked. A worker thread
takes the newest frame at most `rate_hz` times per second, tracks it with the same
`tracking.dic` code as `metarig track`, and hands the poses to a publish callback.
Frames that arrive while the worker is busy are replaced (counted as skipped), which is the
decimation. The first frame tracked after `start` or `reset_reference` becomes the reference
configuration.
"""

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from tracking.dic import DICTracker, FrameError, FramePoses, init_state
from tracking.dic import track_frame as _track_frame

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class PreviewStats:
    """Counters: frames offered by the camera, tracked, and skipped (replaced unseen)."""

    offered: int
    tracked: int
    skipped: int


PublishFn = Callable[[int, FramePoses], None]


def speckle_frame(tracker: DICTracker, seed: int = 0) -> np.ndarray:
    """A uint8 frame of smoothed random speckle as large as the calibration's raw frames (or,
    without one, the units' extent plus a margin): texture everywhere, for warming up."""
    size = tracker.calib.image_size_px
    if size is None:
        w, h = (np.nanmax(tracker.polys_px.reshape(-1, 2), axis=0) + 32).astype(int)
    else:
        w, h = size
    rng = np.random.default_rng(seed)
    noise = rng.random((h + 2, w + 2))
    smooth = (noise[:-2, :-2] + noise[1:-1, 1:-1] + noise[2:, 2:] + noise[1:-1, :-2]
              + noise[:-2, 1:-1]) / 5
    return np.clip(smooth * 255, 0, 255).astype(np.uint8)


class LivePreview:
    """Tracks the newest offered frame at most `rate_hz` times per second on its own thread."""

    def __init__(self, tracker: DICTracker, rate_hz: float, publish: PublishFn,
                 threads: int = 1):
        if not rate_hz > 0:
            raise ValueError(f"rate_hz must be > 0, got {rate_hz}")
        self._tracker = tracker
        self._period = 1.0 / rate_hz
        self._publish = publish
        self._threads = threads
        self._cond = threading.Condition()
        self._slot: tuple[int, np.ndarray] | None = None
        self._state = None
        self._generation = 0  # bumped by reset_reference; stale results are not kept
        self._reference: np.ndarray | None = None  # image of the reference configuration
        self._closed = False
        self._offered = self._tracked = self._skipped = 0
        self._thread = threading.Thread(target=self._run, name="dic-preview", daemon=True)

    @property
    def tracker(self) -> DICTracker:
        return self._tracker

    def warm_up(self) -> float:
        """Compile the tracking kernels now, on a synthetic speckle frame and a shifted copy of
        it, so that the first real frame is tracked at speed (a cold numba cache otherwise costs
        the first frames 10-60 s, longer than a short capture). Returns the wall time it took;
        best effort: a failure is logged and tracking compiles on its first frame instead."""
        t0 = time.monotonic()
        try:
            frame = speckle_frame(self._tracker)
            state = init_state(self._tracker, frame)
            _track_frame(self._tracker, state, np.roll(frame, (1, 2), axis=(0, 1)))
        except Exception:  # noqa: BLE001 - best effort; the real frames say what is wrong
            log.exception("warming up the tracker failed")
        return time.monotonic() - t0

    def start(self) -> "LivePreview":
        self._thread.start()
        return self

    def offer(self, stamp_ns: int, frame: np.ndarray) -> None:
        """Hand over a frame (kept by reference); O(1), never waits for tracking."""
        with self._cond:
            if self._slot is not None:
                self._skipped += 1
            self._slot = (int(stamp_ns), frame)
            self._offered += 1
            self._cond.notify()

    def reset_reference(self, image: np.ndarray | None = None) -> None:
        """Restart from a reference: `image` (e.g. the unloaded sample, in which the next frame's
        units are then searched for), or with None the next tracked frame itself."""
        with self._cond:
            self._state = None
            self._reference = image
            self._generation += 1

    def stats(self) -> PreviewStats:
        with self._cond:
            return PreviewStats(self._offered, self._tracked, self._skipped)

    def close(self, timeout_s: float = 5.0) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify()
        if self._thread.is_alive():
            self._thread.join(timeout_s)

    def _take(self) -> tuple[int, np.ndarray] | None:
        with self._cond:
            while self._slot is None and not self._closed:
                self._cond.wait(0.5)
            if self._closed:
                return None
            item, self._slot = self._slot, None
            return item

    def _run(self) -> None:
        if self._threads > 0:
            import numba

            numba.set_num_threads(min(self._threads, numba.config.NUMBA_NUM_THREADS))
        next_t = time.monotonic()
        while True:
            # wait out the preview period first, then take whatever frame is newest
            delay = next_t - time.monotonic()
            if delay > 0:
                with self._cond:
                    if self._cond.wait_for(lambda: self._closed, delay):
                        return
            item = self._take()
            if item is None:
                return
            next_t = time.monotonic() + self._period
            stamp_ns, frame = item
            try:
                poses = self._track(frame)
            except Exception:
                log.exception("tracking failed on the frame stamped %d ns", stamp_ns)
                continue
            if poses is not None:
                with self._cond:
                    self._tracked += 1
                self._publish(stamp_ns, poses)

    def _track(self, frame: np.ndarray) -> FramePoses | None:
        with self._cond:
            state, generation, reference = self._state, self._generation, self._reference
        if state is None:
            try:
                state = init_state(self._tracker, frame if reference is None else reference)
            except FrameError as exc:
                log.warning("%s unusable as the reference: %s",
                            "frame" if reference is None else "reference image", exc)
                return None
            log.info("reference %s taken (%d units)",
                     "frame" if reference is None else "image", self._tracker.n_units)
        state, poses = _track_frame(self._tracker, state, frame)
        with self._cond:
            if generation == self._generation:
                self._state = state
        if poses.error:
            log.warning("frame unusable, all units flagged lost: %s", poses.error)
        return poses

