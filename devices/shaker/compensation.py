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
    if request.kind not in ("pulse", "burst"):
        raise ValueError(f"compensate a pulse or a burst, not {request.kind!r}")
    t = window(request, rate_hz, cfg.tail_periods)
    a = abs(request.amplitude_m)
    r = request.displacement(t)
    taper = np.ones_like(t)
    tail = t > request.duration_s + 0.5 * (t[-1] - request.duration_s)
    if tail.any():
        x = (t[tail] - t[tail][0]) / max(t[-1] - t[tail][0], 1e-12)
        taper[tail] = 0.5 * (1.0 + np.cos(math.pi * x))
    u = r.copy()
    drive = _samples(limits, u, rate_hz)
    history: list[tuple[float, float, float]] = []

    def result(converged: bool, why: str) -> CompensationResult:
        peaks, rms, drives = zip(*history)
        return CompensationResult(drive, converged, why, peaks, rms, drives)

    for _ in range(cfg.max_iterations):
        y = np.asarray(measure(drive), np.float64)
        if y.shape != u.shape:
            raise ValueError(f"measure returned {y.shape} samples for a drive of {u.shape}")
        peak_err, rms_err = errors(r, y, a)
        history.append((peak_err, rms_err, float(np.max(np.abs(u)))))
        if abs(peak_err) <= cfg.peak_tolerance and rms_err <= cfg.rms_tolerance:
            return result(True, "within the tolerances")
        if len(history) == cfg.max_iterations:
            break
        step = correction(u, y, r, rate_hz, cfg.bandwidth_factor * request.frequency_hz,
                          cfg.gain)
        step = np.clip(step, -cfg.max_step * a, cfg.max_step * a)        # the safety caps
        new = np.clip((u + step) * taper, -cfg.max_drive * a, cfg.max_drive * a)
        new[0] = 0.0
        try:
            drive = _samples(limits, new, rate_hz)
        except LimitError as e:
            return result(False, f"the next drive is outside the limits: {e}")
        u = new
    return result(False, f"not within the tolerances after {cfg.max_iterations} drives")


def _samples(limits: ShakerLimits, u: np.ndarray, rate_hz: float) -> Waveform:
    """The drive `u` (m at `rate_hz`) as a checked 'samples' waveform (`LimitError`)."""
    return make_waveform(limits, WaveformRequest("samples", samples_m=tuple(float(v) for v in u),
                                                 sample_rate_hz=rate_hz))
