"""The shaker port: what the shaker node asks of a shaker and its drive, on the rig clock (s),
in metres. Implemented by `hardware_sim.shaker.SimulatedShaker`; a function-generator drive
implements the same. Requests are checked by `prepare` (the limits, before the drive is
called); a drive only ever plays an accepted `Waveform`."""

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

from devices.limits import LimitError
from devices.shaker.waveform import ShakerLimits, Waveform, WaveformRequest, make_waveform

MAX_DELAY_S = 60.0  # longest accepted wait between a request and its waveform's start


@dataclass(frozen=True, slots=True)
class ShakerReading:
    """The motion sensor at rig time t (s): displacement (m) and velocity (m/s)."""

    t: float
    x_m: float
    v_m_s: float


@runtime_checkable
class ShakerDrive(Protocol):
    """A shaker and what drives it.

    `sensor` says what `read` measures, in words ("": nothing, `read` returns the commanded
    motion: no drive compensation against it). `fault` is "" while the drive is well, else
    one line saying what went wrong on its own (a failed trigger, an instrument error or a
    lost connection seen by a watchdog), after which the drive has been told to stop; a later
    `play` clears it."""

    limits: ShakerLimits
    sensor: str
    fault: str

    @property
    def time_s(self) -> float:
        """Rig time of the last reading (or of `start`), s."""

    def start(self, t_s: float) -> None:
        """The device clock starts at rig time `t_s`, the actuator at rest."""

    def play(self, waveform: Waveform, start_s: float) -> None:
        """Play an accepted waveform from rig time `start_s`; it ends on its own."""

    def stop(self) -> None:
        """Drop any waveform: the actuator returns to rest at zero."""

    def read(self, t_s: float) -> ShakerReading:
        """The measured motion at rig time `t_s` (not before the last reading)."""

    def reconfigure(self, limits: ShakerLimits) -> None:
        """New limits from the node's parameters (for the simulator, its whole configuration,
        which extends the limits); they hold from the next request and reading."""

    def close(self) -> None:
        """Release the device (no waveform plays after this)."""


def prepare(limits: ShakerLimits, request: WaveformRequest, delay_s: float = 0.0) -> Waveform:
    """The waveform of `request`, checked against `limits` and the delay before it starts;
    raises `LimitError` (one line: which limit, and why) before any drive is called."""
    if not 0.0 <= delay_s <= MAX_DELAY_S:
        raise LimitError(f"delay {delay_s} s outside [0, {MAX_DELAY_S:g}] s")
    return make_waveform(limits, request)
