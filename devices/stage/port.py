"""The stage port: what the stage node asks of the pair of linear stages that pre-compress the
sample (they move toward each other symmetrically; the state is the total closing c, m; strain
= c / sample height). Rig clock in s, lengths in m. Implemented by
`hardware_sim.stage.SimulatedStages`; a serial stage controller implements the same. A target
is checked against the limits (`check_strain`) before the stages hear of it."""

import math
from dataclasses import dataclass
from enum import Enum
from typing import Protocol, runtime_checkable

from devices.limits import LimitError
from metarig.fields import param


class StageMode(str, Enum):
    IDLE = "idle"
    MOVING = "moving"
    HOLDING = "holding"
    FAULT = "fault"


@dataclass(frozen=True, slots=True)
class StageLimits:
    """What the stage pair may be asked (SI)."""

    sample_height_m: float = param(0.225, "undeformed sample height that strain refers to, m",
                                   1e-3, 10.0)
    max_strain_rate_per_s: float = param(0.25, "largest allowed closing speed / height, 1/s",
                                         1e-6, 10.0)
    max_strain: float = param(0.09, "largest accepted compressive strain", 0.0, 0.5)
    min_strain: float = param(0.0, "smallest accepted strain (negative: tension)", -0.5, 0.5)

    def __post_init__(self):
        if self.min_strain > self.max_strain:
            raise ValueError("min_strain must not exceed max_strain")


@dataclass(frozen=True, slots=True)
class StageCommand:
    """One command: a new target strain (None: keep), stop (hold where you are), reset."""

    target_strain: float | None = None
    stop: bool = False
    reset: bool = False


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


@dataclass(frozen=True, slots=True)
class StageStatus:
    """Where the stages are: rig time t (s), closing and its target (m), mode, fault reason."""

    t: float
    closing_m: float
    target_m: float
    mode: StageMode
    fault: str = ""


def check_strain(limits: StageLimits, strain: float) -> float:
    """The target closing (m) for a strain, or `LimitError` outside the limits."""
    if not math.isfinite(strain):
        raise LimitError(f"strain must be a finite number, got {strain}")
    if not limits.min_strain <= strain <= limits.max_strain:
        raise LimitError(f"strain {strain:g} outside the limits "
                         f"[{limits.min_strain:g}, {limits.max_strain:g}]")
    return strain * limits.sample_height_m


def check_closing_speed(limits: StageLimits, speed_m_s: float) -> None:
    """ValueError (one line) when a closing speed (m/s) exceeds the strain-rate limit."""
    rate = speed_m_s / limits.sample_height_m
    if rate > limits.max_strain_rate_per_s * (1 + 1e-9):
        raise ValueError(f"closing speed {speed_m_s} m/s is a strain rate of {rate:.3g}/s, "
                         f"above the limit {limits.max_strain_rate_per_s}/s")


@runtime_checkable
class StagePair(Protocol):
    """A pair of linear stages and their controller."""

    limits: StageLimits

    @property
    def time_s(self) -> float:
        """Rig time of the last reading (or of `start`), s."""

    @property
    def status(self) -> StageStatus:
        """The stages' state at the last reading."""

    def start(self, t_s: float) -> None:
        """The controller's clock starts at rig time `t_s` (the stages stay where they are)."""

    def command(self, cmd: StageCommand) -> None:
        """A command that acts at the next reading (a later one before it replaces it)."""

    def read(self, t_s: float) -> StageReading:
        """Advance to rig time `t_s`, apply the pending command, read the encoders."""

    def eta_s(self, strain: float) -> float:
        """Time to reach `strain` from where the stages are, s."""

    def reconfigure(self, limits: StageLimits) -> None:
        """New limits from the node's parameters (for the simulator, its whole configuration,
        which extends the limits); they hold from the next command and reading."""

    def close(self) -> None:
        """Release the controller (the stages hold where they are)."""
