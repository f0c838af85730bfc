"""Simulated low-frequency shaker: waveform requests, limits, second-order actuator, noisy sensor.

The shaker drives the input units of the sample along x. A request (`WaveformRequest`) is
checked against the configured limits and turned into a `Waveform` (a pure function of time);
the actuator follows the commanded displacement through a second-order response

    x'' = wn^2 (x_cmd - x) - 2 zeta wn x',

and a displacement sensor reports x and x' with white noise. Device contract:
`init(cfg, rng) -> ShakerState`, `step(cfg, state, x_cmd, dt, rng) -> (ShakerState, ShakerReading)`.
"""

import math
from dataclasses import dataclass, replace

import numpy as np

from metarig.fields import param

WAVEFORMS = ("pulse", "burst", "samples")


class LimitError(ValueError):
    """A request outside the configured safety limits (the message says which and why)."""


@dataclass(frozen=True, slots=True)
class ShakerConfig:
    """Physical constants and safety limits of the shaker (SI)."""

    natural_frequency_hz: float = param(250.0, "actuator natural frequency wn/2pi, Hz", 1.0, 5000.0)
    damping_ratio: float = param(0.7, "actuator damping ratio zeta", 0.05, 5.0)
    max_amplitude_m: float = param(0.012, "largest accepted peak displacement, m", 0.0, 0.05)
    min_frequency_hz: float = param(1.0, "lowest accepted waveform frequency, Hz", 0.01, 1000.0)
    max_frequency_hz: float = param(200.0, "highest accepted waveform frequency, Hz", 0.01, 1000.0)
    max_velocity_m_s: float = param(2.0, "largest accepted peak commanded velocity, m/s", 0.0, 20.0)
    max_duration_s: float = param(10.0, "longest accepted waveform, s", 0.0, 600.0)
    noise_std_m: float = param(2e-6, "displacement sensor noise (1 sigma), m", 0.0, 1e-3)
    noise_std_m_s: float = param(1e-3, "velocity sensor noise (1 sigma), m/s", 0.0, 1.0)
    max_substep_s: float = param(2e-5, "largest internal integration step, s", 1e-7, 1e-3)

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


def make_waveform(cfg: ShakerConfig, req: WaveformRequest) -> Waveform:
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
        if not cfg.min_frequency_hz <= f <= cfg.max_frequency_hz:
            raise LimitError(f"frequency {f:g} Hz outside the limits "
                             f"[{cfg.min_frequency_hz:g}, {cfg.max_frequency_hz:g}] Hz")
        if req.kind == "burst" and not (0 < req.cycles <= 1000):
            raise LimitError(f"burst cycles must be in (0, 1000], got {req.cycles:g}")
        peak = a
        vmax = (math.pi if req.kind == "pulse" else 2.0 * math.pi) * abs(a) * f
        duration = 1.0 / f if req.kind == "pulse" else req.cycles / f
        wf = Waveform(req.kind, a, f, duration)
    if not 0.0 < peak <= cfg.max_amplitude_m:
        raise LimitError(f"amplitude {peak:g} m outside the limits (0, {cfg.max_amplitude_m:g}] m")
    if vmax > cfg.max_velocity_m_s:
        raise LimitError(f"peak velocity {vmax:.3g} m/s exceeds the limit "
                         f"{cfg.max_velocity_m_s:g} m/s (lower the amplitude or frequency)")
    if duration > cfg.max_duration_s:
        raise LimitError(f"duration {duration:g} s exceeds the limit {cfg.max_duration_s:g} s")
    return wf


@dataclass(frozen=True, slots=True)
class ShakerState:
    """Actuator state: time t (s), displacement x (m), velocity v (m/s)."""

    t: float = 0.0
    x: float = 0.0
    v: float = 0.0


@dataclass(frozen=True, slots=True)
class ShakerReading:
    """Sensor output at time t (s): measured displacement (m) and velocity (m/s)."""

    t: float
    x_m: float
    v_m_s: float


def init(cfg: ShakerConfig, rng: np.random.Generator) -> ShakerState:
    """The shaker at rest at its zero position (t = 0)."""
    del cfg, rng
    return ShakerState()


def step(cfg: ShakerConfig, state: ShakerState, x_cmd: float, dt: float,
         rng: np.random.Generator) -> tuple[ShakerState, ShakerReading]:
    """Advance by dt (s) with the command held at x_cmd (m) (zero-order hold); read the sensor.

    Semi-implicit Euler with sub-steps no longer than `max_substep_s`: with wn*h < 0.1 the
    scheme is stable and its phase error is well under the sensor noise for our waveforms.
    """
    if dt < 0:
        raise ValueError(f"dt must be non-negative, got {dt}")
    wn = 2.0 * math.pi * cfg.natural_frequency_hz
    n = max(1, math.ceil(dt / cfg.max_substep_s))
    h = dt / n
    x, v = state.x, state.v
    for _ in range(n):
        v += h * (wn * wn * (x_cmd - x) - 2.0 * cfg.damping_ratio * wn * v)
        x += h * v
    new = replace(state, t=state.t + dt, x=x, v=v)
    reading = ShakerReading(t=new.t, x_m=x + cfg.noise_std_m * rng.standard_normal(),
                            v_m_s=v + cfg.noise_std_m_s * rng.standard_normal())
    return new, reading


def run(cfg: ShakerConfig, waveform: Waveform, times_s: np.ndarray, start_s: float,
        rng: np.random.Generator, state: ShakerState | None = None
        ) -> tuple[ShakerState, np.ndarray]:
    """Drive the shaker with `waveform` starting at `start_s`, reading at `times_s` (s, increasing).

    Returns the final state and readings [n, 3] (t s, x m, v m/s). The command at each step is
    the waveform value at the start of that step.
    """
    st = init(cfg, rng) if state is None else state
    out = np.empty((len(times_s), 3))
    for i, t in enumerate(np.asarray(times_s, np.float64)):
        cmd = float(waveform.displacement(st.t - start_s))
        st, r = step(cfg, st, cmd, t - st.t, rng)
        out[i] = (r.t, r.x_m, r.v_m_s)
    return st, out


@dataclass(frozen=True, slots=True)
class Program:
    """A waveform scheduled to start at `start_s` (device time, s)."""

    waveform: Waveform
    start_s: float

    @property
    def end_s(self) -> float:
        return self.start_s + self.waveform.duration_s

    def command(self, t_s: float) -> float:
        return float(self.waveform.displacement(t_s - self.start_s))


def advance(cfg: ShakerConfig, state: ShakerState, program: Program | None, t_s: float,
            rng: np.random.Generator, command_step_s: float = 1e-4
            ) -> tuple[ShakerState, ShakerReading]:
    """Advance the shaker to device time `t_s` under `program` (None: hold zero), read once.

    The command is re-sampled every `command_step_s` inside the interval (zero-order hold), so
    the response does not depend on how often a caller happens to advance the device.
    """
    if t_s < state.t:
        raise ValueError(f"time went backwards: {t_s} < {state.t}")
    st = state
    n = max(1, math.ceil((t_s - st.t) / command_step_s - 1e-9))
    h = (t_s - st.t) / n
    quiet = replace(cfg, noise_std_m=0.0, noise_std_m_s=0.0)
    for i in range(n):
        cmd = 0.0 if program is None else program.command(st.t)
        st, reading = step(cfg if i == n - 1 else quiet, st, cmd, h, rng)
    return st, reading
