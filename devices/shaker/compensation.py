"""Drive compensation: iterate the shaker's drive signal until the measured motion matches the
requested waveform (iterative learning control, pure: no ROS, no simulator).

A shaker never moves exactly as commanded: its actuator (and amplifier) has its own dynamics,
so a commanded 7.5 mm pulse is measured as something else (the published experiments measured
7.9-8.7 mm). `compensate` plays a drive, measures the motion it produced (`measure`: the drive's
own sensor, or the tracked input units), and corrects the drive for the next try:

    U_{k+1}(f) = U_k(f) + gain x (R(f) - Y_k(f)) / G_k(f),   G_k = Y_k / U_k,

on the frequencies up to `bandwidth_factor` x the waveform's frequency where the drive has
energy (the plant's response estimated from the last try itself: no model of the shaker is
assumed; above the band nothing is changed, so sensor noise is not amplified). Time series are
zero-padded to twice their length (no wrap-around). The drive covers the request plus
`tail_periods` periods, so the ringing after the pulse can be cancelled too; it starts at zero
and is tapered back to zero over the tail's last half.

Safety cap on every iteration, before anything is played: the change of the drive is clipped
to `max_step` x the amplitude per sample, the drive to `max_drive` x the amplitude, and the new
drive is checked by `make_waveform` against the shaker's limits (amplitude, peak velocity,
duration) as any request is; a drive the limits refuse ends the iteration (`LimitError`, the
result keeps the last good drive). Convergence: the measured peak within `peak_tolerance` of
the requested one and the RMS error over the window within `rms_tolerance` of the amplitude.

`compensate` runs the iteration with a blocking `measure`; `Compensator` is the same iteration
one drive at a time, and `DriveTrials` schedules its drives on a rig clock and gathers their
measurements from a device's periodic readings (the shaker node's `/shaker/compensate`).
"""

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from devices.limits import LimitError
from devices.shaker.waveform import ShakerLimits, Waveform, WaveformRequest, make_waveform
from metarig.fields import param


@dataclass(frozen=True, slots=True)
class CompensationConfig:
    """How the drive is iterated and when it is good enough (fractions of the amplitude)."""

    peak_tolerance: float = param(0.005, "accepted error of the measured peak, fraction", 0.0,
                                  1.0)
    rms_tolerance: float = param(0.01, "accepted RMS error over the window, fraction of the "
                                 "amplitude", 0.0, 1.0)
    max_iterations: int = param(8, "drives played at most, the uncompensated one included",
                                1, 100)
    gain: float = param(0.8, "fraction of the correction applied per iteration", 0.05, 1.0)
    max_step: float = param(0.3, "largest change of the drive in one iteration, fraction of "
                            "the amplitude", 0.01, 2.0)
    max_drive: float = param(1.5, "largest drive, fraction of the amplitude (also within the "
                             "shaker's limits)", 1.0, 5.0)
    bandwidth_factor: float = param(8.0, "corrections up to this multiple of the waveform's "
                                    "frequency", 1.0, 100.0)
    tail_periods: float = param(0.5, "drive beyond the request (ringing), periods", 0.0, 10.0)
    rest_s: float = param(0.05, "rest between two drives played on a rig (the shaker comes to "
                          "rest), s", 0.0, 60.0)


@dataclass(frozen=True, slots=True)
class CompensationResult:
    """The drive to play (`drive`: a 'samples' waveform), whether it met the tolerances, why it
    stopped, and per drive played (oldest first): the measured peak error and RMS error
    (fractions of the amplitude) and the drive's peak (m)."""

    drive: Waveform
    converged: bool
    stopped: str
    peak_errors: tuple[float, ...]
    rms_errors: tuple[float, ...]
    drive_peaks_m: tuple[float, ...]


def window(request: Waveform, rate_hz: float, tail_periods: float) -> np.ndarray:
    """[n] sample times of the drive (s from its start): the request and its tail."""
    period = 1.0 / request.frequency_hz if request.frequency_hz > 0 else request.duration_s
    n = int(math.floor((request.duration_s + tail_periods * period) * rate_hz)) + 1
    return np.arange(n) / rate_hz


def errors(r: np.ndarray, y: np.ndarray, amplitude_m: float) -> tuple[float, float]:
    """(peak error, RMS error) of the measured `y` against the requested `r`, as fractions of
    the amplitude; the peak is the largest displacement from rest, with its sign."""
    peak_r = r[np.argmax(np.abs(r))]
    peak_y = y[np.argmax(np.abs(y))]
    return (float(peak_y - peak_r) / amplitude_m,
            float(np.sqrt(np.mean((y - r) ** 2))) / amplitude_m)


def correction(u: np.ndarray, y: np.ndarray, r: np.ndarray, rate_hz: float, band_hz: float,
               gain: float) -> np.ndarray:
    """[n] the change of the drive `u` that the inverse of the response estimated from this
    try (`y` measured under `u`) predicts to bring `y` to `r`, within `band_hz`."""
    n = u.size
    m = 2 * n  # zero-padded: the responses do not wrap around
    uf, yf, rf = (np.fft.rfft(x, m) for x in (u, y, r))
    freqs = np.fft.rfftfreq(m, 1.0 / rate_hz)
    strong = (np.abs(uf) > 1e-3 * np.abs(uf).max()) & (np.abs(yf) > 1e-3 * np.abs(yf).max())
    use = (freqs <= band_hz) & strong
    step = np.zeros_like(uf)
    step[use] = gain * (rf[use] - yf[use]) * uf[use] / yf[use]
    return np.fft.irfft(step, m)[:n]


class Compensator:
    """The iteration of `compensate` one drive at a time, for a caller that plays the drives
    on its own clock (the shaker node): play `drive` from rest, sample the measured
    displacement at `times_s` after its start, hand it to `measured`; `result` is set (and
    `drive` is the one to play) once the iteration is over."""

    def __init__(self, request: Waveform, limits: ShakerLimits, rate_hz: float,
                 cfg: CompensationConfig = CompensationConfig()):
        if request.kind not in ("pulse", "burst"):
            raise ValueError(f"compensate a pulse or a burst, not {request.kind!r}")
        self.request, self.limits, self.rate_hz, self.cfg = request, limits, rate_hz, cfg
        t = window(request, rate_hz, cfg.tail_periods)
        self.times_s = t
        self._r = request.displacement(t)
        self._taper = np.ones_like(t)
        tail = t > request.duration_s + 0.5 * (t[-1] - request.duration_s)
        if tail.any():
            x = (t[tail] - t[tail][0]) / max(t[-1] - t[tail][0], 1e-12)
            self._taper[tail] = 0.5 * (1.0 + np.cos(math.pi * x))
        self._u = self._r.copy()
        self.drive = drive_waveform(limits, self._u, rate_hz)
        self._history: list[tuple[float, float, float]] = []
        self.result: CompensationResult | None = None

    def measured(self, y: np.ndarray) -> CompensationResult | None:
        """Take the displacement [n] (m, at `times_s`) that `drive` produced; the next drive
        is then in `drive`, or the iteration is over and its result returned (and kept)."""
        if self.result is not None:
            raise RuntimeError("the compensation is over")
        cfg, a = self.cfg, abs(self.request.amplitude_m)
        y = np.asarray(y, np.float64)
        if y.shape != self._u.shape:
            raise ValueError(f"measure returned {y.shape} samples for a drive of "
                             f"{self._u.shape}")
        peak_err, rms_err = errors(self._r, y, a)
        self._history.append((peak_err, rms_err, float(np.max(np.abs(self._u)))))
        if abs(peak_err) <= cfg.peak_tolerance and rms_err <= cfg.rms_tolerance:
            return self._end(True, "within the tolerances")
        if len(self._history) == cfg.max_iterations:
            return self._end(False, f"not within the tolerances after {cfg.max_iterations} "
                             "drives")
        step = correction(self._u, y, self._r, self.rate_hz,
                          cfg.bandwidth_factor * self.request.frequency_hz, cfg.gain)
        step = np.clip(step, -cfg.max_step * a, cfg.max_step * a)        # the safety caps
        new = np.clip((self._u + step) * self._taper, -cfg.max_drive * a, cfg.max_drive * a)
        new[0] = 0.0
        try:
            drive = drive_waveform(self.limits, new, self.rate_hz)
        except LimitError as e:
            return self._end(False, f"the next drive is outside the limits: {e}")
        self._u, self.drive = new, drive
        return None

    def _end(self, converged: bool, why: str) -> CompensationResult:
        peaks, rms, drives = zip(*self._history)
        self.result = CompensationResult(self.drive, converged, why, peaks, rms, drives)
        return self.result


def compensate(request: Waveform, limits: ShakerLimits,
               measure: Callable[[Waveform], np.ndarray], rate_hz: float,
               cfg: CompensationConfig = CompensationConfig()) -> CompensationResult:
    """Iterate a drive for `request` (an accepted pulse or burst) until the measured motion
    matches it (see the module docstring).

    Args:
        request: the waveform wanted at the shaker (m).
        limits: the shaker's limits, which every drive must pass.
        measure: plays a drive from rest and returns the measured displacement (m) at the
            drive's sample times (`window`: [n], from the drive's start, at `rate_hz`).
        rate_hz: the drive's and the measurement's sample rate, Hz.
        cfg: tolerances, gain and the safety caps.
    """
    c = Compensator(request, limits, rate_hz, cfg)
    while c.result is None:
        c.measured(measure(c.drive))
    return c.result


class DriveTrials:
    """The drives of a `Compensator` played one after another on a device read every
    `1 / rate_hz` s of rig time (k / rate_hz, as the shaker node reads it): each drive starts
    on a reading time, `rest_s` after the last reading of the drive before (the first at
    `first_s` or after), so that its measured window holds readings only; `take` files each
    reading of the device's sensor and hands a full window to the compensator."""

    def __init__(self, compensator: Compensator, first_s: float):
        self.compensator = compensator
        self._period = 1.0 / compensator.rate_hz
        self._n = compensator.times_s.size
        self._start(first_s)

    def _start(self, t_s: float) -> None:
        self.start_s = math.ceil(t_s / self._period - 1e-9) * self._period
        self._y = np.full(self._n, np.nan)
        self.pending = True   # the drive is still to be handed to the device (`play`)

    def play(self) -> tuple[Waveform, float]:
        """The drive to play now and its start (rig time, s); hand it to the device before the
        first reading at or after that start."""
        self.pending = False
        return self.compensator.drive, self.start_s

    def take(self, t_s: float, x_m: float) -> CompensationResult | None:
        """File the reading at rig time `t_s` (s; displacement `x_m`, m). The result once the
        iteration is over; `ValueError` when a window lacks readings (a device read less
        often than `rate_hz`)."""
        i = round((t_s - self.start_s) / self._period)
        if self.pending or i < 0:
            return None
        if i < self._n:
            self._y[i] = x_m
        if i < self._n - 1:
            return None
        missing = int(np.isnan(self._y).sum())
        if missing:
            raise ValueError(f"{missing} of the {self._n} readings of a drive are missing "
                             f"(the device was read less often than {1 / self._period:g} Hz)")
        result = self.compensator.measured(self._y)
        if result is None:
            self._start(t_s + self.compensator.cfg.rest_s)
        return result


def drive_waveform(limits: ShakerLimits, u: np.ndarray, rate_hz: float) -> Waveform:
    """The drive `u` [n] (m at `rate_hz`, from rest) as a 'samples' waveform checked against
    `limits` (`LimitError`): every drive, and a kept one again before it is played."""
    return make_waveform(limits, WaveformRequest("samples", samples_m=tuple(float(v) for v in u),
                                                 sample_rate_hz=rate_hz))
