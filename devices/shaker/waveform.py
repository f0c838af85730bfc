"""Shaker waveforms: a request (`WaveformRequest`) checked against the limits (`ShakerLimits`)
becomes a `Waveform`, a pure function of time, scheduled as a `Program`. Shared by every shaker
drive (the simulated one, a function generator) and checked before any of them is called."""

import math
from dataclasses import dataclass

import numpy as np

from devices.limits import LimitError
from metarig.fields import param

WAVEFORMS = ("pulse", "burst", "samples")


@dataclass(frozen=True, slots=True)
class ShakerLimits:
    """What a shaker may be asked (SI)."""

    max_amplitude_m: float = param(0.012, "largest accepted peak displacement, m", 0.0, 0.05)
    min_frequency_hz: float = param(1.0, "lowest accepted waveform frequency, Hz", 0.01, 1000.0)
    max_frequency_hz: float = param(200.0, "highest accepted waveform frequency, Hz", 0.01, 1000.0)
    max_velocity_m_s: float = param(2.0, "largest accepted peak commanded velocity, m/s", 0.0, 20.0)
    max_duration_s: float = param(10.0, "longest accepted waveform, s", 0.0, 600.0)

    def __post_init__(self):
        if self.min_frequency_hz >= self.max_frequency_hz:
            raise ValueError("min_frequency_hz must be below max_frequency_hz")


@dataclass(frozen=True, slots=True)
class WaveformRequest:
    """What an operator asks for (unchecked).

    Attributes:
        kind: "pulse" (A/2 (1 - cos 2 pi f t), one period), "burst" (A sin 2 pi f t over `cycles`
            periods) or "samples" (a recorded displacement signal at `sample_rate_hz`).
        amplitude_m: A, m (pulse, burst).
        frequency_hz: f, Hz (pulse, burst).
        cycles: burst length in periods.
        samples_m: displacement samples, m ("samples").
        sample_rate_hz: rate of `samples_m`, Hz.
    """

    kind: str = "pulse"
    amplitude_m: float = 0.0075
    frequency_hz: float = 30.0
    cycles: float = 1.0
    samples_m: tuple[float, ...] = ()
    sample_rate_hz: float = 0.0


@dataclass(frozen=True, slots=True)
class Waveform:
    """An accepted displacement command u(t) on [0, duration_s] (zero before and after), SI."""

    kind: str
    amplitude_m: float
    frequency_hz: float
    duration_s: float
    samples_m: np.ndarray | None = None
    sample_rate_hz: float = 0.0

    def displacement(self, t_s) -> np.ndarray:
        """u(t), m, for times t (s) relative to the waveform start; any shape."""
        t = np.asarray(t_s, np.float64)
        inside = (t >= 0.0) & (t <= self.duration_s)
        w = 2.0 * math.pi * self.frequency_hz
        if self.kind == "pulse":
            u = 0.5 * self.amplitude_m * (1.0 - np.cos(w * t))
        elif self.kind == "burst":
            u = self.amplitude_m * np.sin(w * t)
        else:
            ts = np.arange(self.samples_m.size) / self.sample_rate_hz
            u = np.interp(t, ts, self.samples_m)
        return np.where(inside, u, 0.0)

    def velocity(self, t_s) -> np.ndarray:
        """du/dt, m/s (finite differences for recorded samples)."""
        t = np.asarray(t_s, np.float64)
        inside = (t >= 0.0) & (t <= self.duration_s)
        w = 2.0 * math.pi * self.frequency_hz
        if self.kind == "pulse":
            v = 0.5 * self.amplitude_m * w * np.sin(w * t)
        elif self.kind == "burst":
            v = self.amplitude_m * w * np.cos(w * t)
        else:
            ts = np.arange(self.samples_m.size) / self.sample_rate_hz
            v = np.interp(t, ts, np.gradient(self.samples_m, ts))
        return np.where(inside, v, 0.0)


def make_waveform(limits: ShakerLimits, req: WaveformRequest) -> Waveform:
    """Check a request against the limits and build its waveform; raises `LimitError`."""
    if req.kind not in WAVEFORMS:
        raise LimitError(f"unknown waveform {req.kind!r}; choose one of {', '.join(WAVEFORMS)}")
    if req.kind == "samples":
        s = np.asarray(req.samples_m, np.float64)
        if s.ndim != 1 or s.size < 2 or not np.all(np.isfinite(s)):
            raise LimitError("a 'samples' waveform needs at least 2 finite samples")
        if not (math.isfinite(req.sample_rate_hz) and req.sample_rate_hz > 0):
            raise LimitError(f"sample_rate_hz must be positive, got {req.sample_rate_hz}")
        peak = float(np.max(np.abs(s)))
        vmax = float(np.max(np.abs(np.diff(s)))) * req.sample_rate_hz
        duration = (s.size - 1) / req.sample_rate_hz
        wf = Waveform("samples", peak, 0.0, duration, s, req.sample_rate_hz)
    else:
        a, f = req.amplitude_m, req.frequency_hz
        if not (math.isfinite(a) and math.isfinite(f)):
            raise LimitError("amplitude and frequency must be finite numbers")
        if not limits.min_frequency_hz <= f <= limits.max_frequency_hz:
            raise LimitError(f"frequency {f:g} Hz outside the limits "
                             f"[{limits.min_frequency_hz:g}, {limits.max_frequency_hz:g}] Hz")
        if req.kind == "burst" and not (0 < req.cycles <= 1000):
            raise LimitError(f"burst cycles must be in (0, 1000], got {req.cycles:g}")
        peak = a
        vmax = (math.pi if req.kind == "pulse" else 2.0 * math.pi) * abs(a) * f
        duration = 1.0 / f if req.kind == "pulse" else req.cycles / f
        wf = Waveform(req.kind, a, f, duration)
    if not 0.0 < peak <= limits.max_amplitude_m:
        raise LimitError(f"amplitude {peak:g} m outside the limits (0, {limits.max_amplitude_m:g}] m")
    if vmax > limits.max_velocity_m_s:
        raise LimitError(f"peak velocity {vmax:.3g} m/s exceeds the limit "
                         f"{limits.max_velocity_m_s:g} m/s (lower the amplitude or frequency)")
    if duration > limits.max_duration_s:
        raise LimitError(f"duration {duration:g} s exceeds the limit {limits.max_duration_s:g} s")
    return wf


@dataclass(frozen=True, slots=True)
class Program:
    """A waveform scheduled to start at `start_s` (rig time, s)."""

    waveform: Waveform
    start_s: float

    @property
    def end_s(self) -> float:
        return self.start_s + self.waveform.duration_s

    def command(self, t_s: float) -> float:
        return float(self.waveform.displacement(t_s - self.start_s))
