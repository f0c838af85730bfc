"""Simulated low-frequency shaker: second-order actuator, noisy sensor, and `SimulatedShaker`,
the shaker port (`devices.shaker.port.ShakerDrive`) on top of them.

The shaker drives the input units of the sample along x. Requests are checked and turned into
waveforms by the port (`devices.shaker.waveform`); the actuator follows the commanded
displacement through a second-order response

    x'' = wn^2 (x_cmd - x) - 2 zeta wn x',

and a displacement sensor reports x and x' with white noise. Device contract:
`init(cfg, rng) -> ShakerState`, `step(cfg, state, x_cmd, dt, rng) -> (ShakerState, ShakerReading)`.
"""

import math
from dataclasses import dataclass, replace

import numpy as np

from devices.shaker.port import ShakerReading
from devices.shaker.waveform import Program, ShakerLimits, Waveform
from metarig.fields import param

@dataclass(frozen=True, slots=True)
class ShakerConfig(ShakerLimits):
    """The simulated shaker: its safety limits (`ShakerLimits`, the fields before these) and
    its physics (SI)."""

    natural_frequency_hz: float = param(250.0, "actuator natural frequency wn/2pi, Hz", 1.0, 5000.0)
    damping_ratio: float = param(0.7, "actuator damping ratio zeta", 0.05, 5.0)
    noise_std_m: float = param(2e-6, "displacement sensor noise (1 sigma), m", 0.0, 1e-3)
    noise_std_m_s: float = param(1e-3, "velocity sensor noise (1 sigma), m/s", 0.0, 1.0)
    max_substep_s: float = param(2e-5, "largest internal integration step, s", 1e-7, 1e-3)


@dataclass(frozen=True, slots=True)
class ShakerState:
    """Actuator state: time t (s), displacement x (m), velocity v (m/s)."""

    t: float = 0.0
    x: float = 0.0
    v: float = 0.0


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


class SimulatedShaker:
    """The simulated shaker behind the shaker port (`devices.shaker.port.ShakerDrive`): the
    actuator and sensor above, advanced on the rig clock as readings are asked for."""

    def __init__(self, cfg: ShakerConfig, rng: np.random.Generator):
        self.cfg, self.limits, self._rng = cfg, cfg, rng
        self.fault = ""  # a simulated actuator does not fail
        self._state = init(cfg, rng)
        self._program: Program | None = None

    @property
    def time_s(self) -> float:
        return self._state.t

    def start(self, t_s: float) -> None:
        self._state = replace(self._state, t=float(t_s))

    def play(self, waveform: Waveform, start_s: float) -> None:
        self._program = Program(waveform, float(start_s))

    def stop(self) -> None:
        self._program = None

    def read(self, t_s: float) -> ShakerReading:
        self._state, reading = advance(self.cfg, self._state, self._program, t_s, self._rng)
        if self._program is not None and self._state.t > self._program.end_s:
            self._program = None
        return reading

    @property
    def sensor(self) -> str:
        return (f"the simulated shaker's displacement sensor (noise {self.cfg.noise_std_m:g} m "
                "rms)")

    def reconfigure(self, cfg: ShakerConfig) -> None:
        self.cfg = self.limits = cfg

    def close(self) -> None:
        self._program = None
