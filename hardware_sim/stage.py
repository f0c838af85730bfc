"""Simulated pair of linear stages that pre-compress the sample (top and bottom rows), and
`SimulatedStages`, the stage port (`devices.stage.port.StagePair`) on top of it.

The two stages move toward each other symmetrically. Their state is the total closing
displacement c (m; strain = c / sample height). A target strain is checked against the limits,
then the stages move at a limited closing speed (trapezoid-free: constant speed, the real stages
are quasi-static), hold at the target, and report noisy encoder positions. A simulated jam
(`jam_closing_m`) makes the stage stop short of its command; the following-error check then
puts it in FAULT until a reset. Device contract: `init(cfg, rng) -> StageState`,
`step(cfg, state, cmd, dt, rng) -> (StageState, StageReading)`.
"""

import math
from dataclasses import dataclass, replace

import numpy as np

from devices.limits import LimitError
from devices.stage.port import (
    StageCommand,
    StageLimits,
    StageMode,
    StageReading,
    StageStatus,
    check_closing_speed,
    check_strain,
)
from metarig.fields import param


@dataclass(frozen=True, slots=True)
class StageConfig(StageLimits):
    """The simulated stage pair: its limits (`StageLimits`, the fields before these) and its
    mechanics (SI)."""

    closing_speed_m_s: float = param(0.05625, "total closing speed while moving, m/s", 1e-6, 1.0)
    position_tolerance_m: float = param(2e-6, "distance at which a move counts as arrived, m",
                                     0.0, 1e-2)
    following_error_m: float = param(5e-4, "command-position mismatch that trips a fault, m",
                                  1e-6, 1e-1)
    noise_std_m: float = param(1e-6, "encoder noise (1 sigma), m", 0.0, 1e-3)
    jam_closing_m: float = param(math.inf, "simulated jam: the stages cannot close beyond this, m",
                              0.0, math.inf)

    def __post_init__(self):
        check_closing_speed(self, self.closing_speed_m_s)
        StageLimits.__post_init__(self)


@dataclass(frozen=True, slots=True)
class StageState:
    """t (s); closing c and its set-point (m); target (m); mode; fault reason."""

    t: float = 0.0
    closing_m: float = 0.0
    setpoint_m: float = 0.0
    target_m: float = 0.0
    mode: StageMode = StageMode.IDLE
    fault: str = ""


def eta_s(cfg: StageConfig, state: StageState, strain: float) -> float:
    """Time to reach `strain` from the current position at the configured speed, s."""
    return abs(strain * cfg.sample_height_m - state.closing_m) / cfg.closing_speed_m_s


def init(cfg: StageConfig, rng: np.random.Generator) -> StageState:
    """Stages at their zero (undeformed) position, idle."""
    del cfg, rng
    return StageState()


def step(cfg: StageConfig, state: StageState, cmd: StageCommand, dt: float,
         rng: np.random.Generator) -> tuple[StageState, StageReading]:
    """Apply `cmd`, advance by dt (s), read the encoders. A bad target raises `LimitError`."""
    if dt < 0:
        raise ValueError(f"dt must be non-negative, got {dt}")
    s = state
    if cmd.reset and s.mode == StageMode.FAULT:
        s = replace(s, mode=StageMode.IDLE, fault="", setpoint_m=s.closing_m, target_m=s.closing_m)
    if cmd.stop and s.mode != StageMode.FAULT:
        s = replace(s, target_m=s.closing_m, setpoint_m=s.closing_m,
                    mode=StageMode.HOLDING if s.mode != StageMode.IDLE else StageMode.IDLE)
    elif cmd.target_strain is not None:
        if s.mode == StageMode.FAULT:
            raise LimitError(f"stages are in FAULT ({s.fault}); reset them first")
        s = replace(s, target_m=check_strain(cfg, cmd.target_strain), mode=StageMode.MOVING)
    if s.mode == StageMode.MOVING:
        # constant-speed set-point toward the target; the mechanism follows it unless jammed
        gap = s.target_m - s.setpoint_m
        setpoint = s.setpoint_m + math.copysign(min(abs(gap), cfg.closing_speed_m_s * dt), gap)
        closing = min(setpoint, cfg.jam_closing_m)
        s = replace(s, setpoint_m=setpoint, closing_m=closing)
        if abs(setpoint - closing) > cfg.following_error_m:
            s = replace(s, mode=StageMode.FAULT,
                        fault=f"following error {abs(setpoint - closing):.2e} m at closing "
                              f"{closing:.5f} m (jammed?)")
        elif abs(s.target_m - closing) <= cfg.position_tolerance_m:
            s = replace(s, closing_m=s.target_m, setpoint_m=s.target_m, mode=StageMode.HOLDING)
    s = replace(s, t=state.t + dt)
    half = 0.5 * s.closing_m
    reading = StageReading(t=s.t, bottom_m=half + cfg.noise_std_m * rng.standard_normal(),
                           top_m=half + cfg.noise_std_m * rng.standard_normal(), mode=s.mode,
                           target_strain=s.target_m / cfg.sample_height_m)
    return s, reading


class SimulatedStages:
    """The simulated stages behind the stage port (`devices.stage.port.StagePair`), advanced on
    the rig clock as readings are asked for; a command acts at the next reading."""

    def __init__(self, cfg: StageConfig, rng: np.random.Generator):
        self.cfg, self.limits, self._rng = cfg, cfg, rng
        self._state = init(cfg, rng)
        self._pending = StageCommand()

    @property
    def time_s(self) -> float:
        return self._state.t

    @property
    def status(self) -> StageStatus:
        s = self._state
        return StageStatus(s.t, s.closing_m, s.target_m, s.mode, s.fault)

    def start(self, t_s: float) -> None:
        self._state = replace(self._state, t=float(t_s))

    def command(self, cmd: StageCommand) -> None:
        self._pending = cmd

    def read(self, t_s: float) -> StageReading:
        cmd, self._pending = self._pending, StageCommand()
        self._state, reading = step(self.cfg, self._state, cmd, t_s - self._state.t, self._rng)
        return reading

    def eta_s(self, strain: float) -> float:
        return eta_s(self.cfg, self._state, strain)

    def reconfigure(self, cfg: StageConfig) -> None:
        self.cfg = self.limits = cfg

    def close(self) -> None:
        self._pending = StageCommand()
