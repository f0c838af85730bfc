"""Simulated pair of linear stages that pre-compress the sample (top and bottom rows).

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
from enum import Enum

import numpy as np

from devices.limits import LimitError
from metarig.fields import param


class StageMode(str, Enum):
    IDLE = "idle"
    MOVING = "moving"
    HOLDING = "holding"
    FAULT = "fault"


@dataclass(frozen=True, slots=True)
class StageConfig:
    """Constants and limits of the stage pair (SI)."""

    sample_height_m: float = param(0.225, "undeformed sample height that strain refers to, m",
                                1e-3, 10.0)
    closing_speed_m_s: float = param(0.05625, "total closing speed while moving, m/s", 1e-6, 1.0)
    max_strain_rate_per_s: float = param(0.25, "largest allowed closing speed / height, 1/s",
                                      1e-6, 10.0)
    max_strain: float = param(0.09, "largest accepted compressive strain", 0.0, 0.5)
    min_strain: float = param(0.0, "smallest accepted strain (negative: tension)", -0.5, 0.5)
    position_tolerance_m: float = param(2e-6, "distance at which a move counts as arrived, m",
                                     0.0, 1e-2)
    following_error_m: float = param(5e-4, "command-position mismatch that trips a fault, m",
                                  1e-6, 1e-1)
    noise_std_m: float = param(1e-6, "encoder noise (1 sigma), m", 0.0, 1e-3)
    jam_closing_m: float = param(math.inf, "simulated jam: the stages cannot close beyond this, m",
                              0.0, math.inf)

    def __post_init__(self):
        if self.closing_speed_m_s / self.sample_height_m > self.max_strain_rate_per_s * (1 + 1e-9):
            raise ValueError(
                f"closing speed {self.closing_speed_m_s} m/s is a strain rate of "
                f"{self.closing_speed_m_s / self.sample_height_m:.3g}/s, above the limit "
                f"{self.max_strain_rate_per_s}/s")
        if self.min_strain > self.max_strain:
            raise ValueError("min_strain must not exceed max_strain")


@dataclass(frozen=True, slots=True)
class StageCommand:
    """One step's command: a new target strain (None: keep), stop (hold where you are), reset."""

    target_strain: float | None = None
    stop: bool = False
    reset: bool = False


@dataclass(frozen=True, slots=True)
class StageState:
    """t (s); closing c and its set-point (m); target (m); mode; fault reason."""

    t: float = 0.0
    closing_m: float = 0.0
    setpoint_m: float = 0.0
    target_m: float = 0.0
    mode: StageMode = StageMode.IDLE
    fault: str = ""


@dataclass(frozen=True, slots=True)
class StageReading:
    """Encoder output: t (s), bottom and top stage positions (m, toward each other positive)."""

    t: float
    bottom_m: float
    top_m: float
    mode: StageMode
    target_strain: float

    @property
    def closing_m(self) -> float:
        return self.bottom_m + self.top_m


def check_strain(cfg: StageConfig, strain: float) -> float:
    """The target closing (m) for a strain, or `LimitError` outside the limits."""
    if not math.isfinite(strain):
        raise LimitError(f"strain must be a finite number, got {strain}")
    if not cfg.min_strain <= strain <= cfg.max_strain:
        raise LimitError(f"strain {strain:g} outside the limits "
                         f"[{cfg.min_strain:g}, {cfg.max_strain:g}]")
    return strain * cfg.sample_height_m


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
