"""Composition of the simulated rig: measured device motion -> specimen -> camera footage.

Order of the batch (see `hardware_sim.specimen`): the shaker and stages are simulated live from
their commands (their nodes publish what their sensors read); once the capture window is over,
the specimen is solved under that measured motion, and the frames of the window are rendered at
the camera rate, each blurred over its exposure and stamped at the middle of it, with the poses
at the stamp kept as ground truth (the pose a tracker measures in a blurred frame).
"""

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from hardware_sim import camera as cam
from hardware_sim.specimen import Specimen, simulate


@dataclass(frozen=True)
class MotionRecord:
    """A measured 1-D signal: t [n] s increasing, value [n] (m)."""

    t: np.ndarray
    value: np.ndarray

    @classmethod
    def from_samples(cls, samples: list[tuple[float, float]], t_end: float) -> "MotionRecord":
        """Sorted, de-duplicated samples up to `t_end`, starting at rest at t = 0 and held from
        the last of them to `t_end`.

        Samples after `t_end` are left out: how many of them have arrived when the capture is
        developed depends on the machine's load, and the record's end sets the resampling of
        the shaker's record (`design_engine.solve.run.smooth_input` fits a spline over the
        whole record on a grid spanning it), so with them the same device motion gave a
        different specimen motion under load.
        """
        if samples:
            a = np.array(sorted(samples))
            t, keep = np.unique(a[:, 0], return_index=True)
            v = a[keep, 1]
            inside = t <= t_end
            t, v = t[inside], v[inside]
        else:
            t, v = np.zeros(0), np.zeros(0)
        if t.size == 0 or t[0] > 0:
            t, v = np.r_[0.0, t], np.r_[0.0, v]
        if t[-1] < t_end:
            t, v = np.r_[t, t_end], np.r_[v, v[-1]]
        return cls(t, v)


def record_complete(sample_t_s, t_end: float) -> bool:
    """Whether a device's samples (times, s, any order) hold every sample up to `t_end`: one
    after it, or a last one less than one sampling period (the median step of the last 20)
    before it, so that the next is due after it. A device samples at its own rate on the rig
    clock: the sample due at `t_end` itself may still be in flight when the capture stops, and
    a record that ends one sample early is held at its last value instead (a different
    specimen motion at the last frames)."""
    t = np.sort(np.asarray(sample_t_s, np.float64))
    if t.size == 0:
        return False
    if t[-1] >= t_end:
        return True
    if t.size < 2:
        return False
    period = float(np.median(np.diff(t[-20:])))
    # stamps are integer ns: a step's rounding is far below this tolerance
    return bool(t[-1] + period > t_end + min(1e-6, 0.01 * period))


def capture_times(t_start_s: float, t_stop_s: float, fps: float) -> np.ndarray:
    """Frame times k / fps (absolute multiples of the frame period) inside [t_start, t_stop]."""
    k0, k1 = int(np.ceil(t_start_s * fps - 1e-9)), int(np.floor(t_stop_s * fps + 1e-9))
    k0 = max(k0, 1)  # t = 0 is the rest state: the first frame is one period later
    return np.arange(k0, k1 + 1) / fps


def _solve(specimen: Specimen, times: np.ndarray, shaker: MotionRecord, stage: MotionRecord | None):
    """The specimen's motion at `times` (s) under the device records."""
    return simulate(
        specimen,
        times,
        shaker.t,
        shaker.value,
        None if stage is None else stage.t,
        None if stage is None else stage.value,
    )


def specimen_motion(
    specimen: Specimen,
    frame_t_s: np.ndarray,
    shaker: MotionRecord,
    stage: MotionRecord | None,
    fps: float,
):
    """Solve the specimen at the frame times and one period before the first."""
    times = np.r_[frame_t_s[0] - 1.0 / fps, frame_t_s]
    return _solve(specimen, times, shaker, stage)


# exposure of a frame, in frame periods: it ends at the frame's capture time k / fps
SHUTTER = 0.5


def exposure_times(frame_t_s: np.ndarray, fps: float, shutter: float = SHUTTER) -> np.ndarray:
    """[n, 3] start, middle and end of each frame's exposure, s (the end at the frame time)."""
    if not 0.0 < shutter < 1.0:
        raise ValueError(f"shutter must be in (0, 1) frame periods, got {shutter}")
    end = np.asarray(frame_t_s, np.float64)
    return np.stack([end - shutter / fps, end - 0.5 * shutter / fps, end], axis=1)


def exposure_motion(
    specimen: Specimen,
    frame_t_s: np.ndarray,
    shaker: MotionRecord,
    stage: MotionRecord | None,
    fps: float,
    shutter: float = SHUTTER,
):
    """Solve the specimen at the start, middle and end of every frame's exposure (`film`)."""
    times = exposure_times(frame_t_s, fps, shutter).ravel()
    return _solve(specimen, times, shaker, stage)


def film(
    specimen: Specimen,
    cfg: cam.CameraConfig,
    traj,
    rng: np.random.Generator,
) -> Iterator[tuple[float, np.ndarray, np.ndarray]]:
    """Render the frames of an `exposure_motion` trajectory.

    Each frame is blurred over its exposure (poses linear from its start to its end) and is
    stamped at the middle of the exposure, where the motion it shows is centred. Yields (t s,
    uint8 [H, W] frame, [n_units, 3] true pose (u, v, theta) at t, the middle of the exposure).
    """
    textures = cam.make_speckle_textures(specimen.polygons_m, cfg, rng)
    if len(traj.t) % 3:
        raise ValueError("film takes an exposure_motion trajectory (start, middle, end per frame)")
    for k in range(0, len(traj.t), 3):
        frame = cam.render_frame(
            cfg, specimen.polygons_m, traj.q[k + 2], textures, rng, motion_from=traj.q[k]
        )
        yield float(traj.t[k + 1]), frame, traj.q[k + 1]


def reference_frame(
    specimen: Specimen, cfg: cam.CameraConfig, seed: int, frames: int = cam.REFERENCE_FRAMES
) -> np.ndarray:
    """The unloaded specimen at rest (uint8 [H, W]), averaged over `frames` frames, with the
    speckle that `film` draws from `np.random.default_rng(seed)`: the image a lab takes before
    the stages close (`hardware_sim.camera.reference_image`)."""
    return cam.reference_image(cfg, specimen.polygons_m, seed, frames)


def centred_origin(
    polygons_m: np.ndarray, width_px: int, height_px: int, m_per_px: float
) -> tuple[float, float]:
    """Pixel position of the sample-frame origin that centres the sample in the frame (y up)."""
    lo, hi = polygons_m.reshape(-1, 2).min(axis=0), polygons_m.reshape(-1, 2).max(axis=0)
    centre = 0.5 * (lo + hi)
    return (
        (width_px - 1) / 2.0 - centre[0] / m_per_px,
        (height_px - 1) / 2.0 + centre[1] / m_per_px,
    )
