"""The stage pair on Zaber linear stages over a serial port (pyserial), speaking the Zaber ASCII
protocol: the stage port (`devices.stage.port.StagePair`).

Two axes close the gap symmetrically, each half the closing: two devices in a daisy chain
(the default, devices 1 and 2, axis 1) or two axes of one controller. Commands are
`/<device> <axis> <command>` lines; replies `@<device> <axis> <OK|RJ> <IDLE|BUSY> <flag>
<data>` (flag `--` when clear; F.. faults, W.. warnings, N.. notices). Positions are in
microsteps; `microstep_m` (the stage's Microstep Size) converts them, and `direction` and
`zero_steps` map each stage's position to its share of the closing (toward the other stage
positive; zero at the undeformed sample). The protocol was checked against Zaber's ASCII
protocol as the zproto library documents it (replies, status, flag classes); the maxspeed unit
(data = microsteps/s x 1.6384) is from Zaber's manual as remembered, not checked here: verify
it on the stages (`get maxspeed` against a timed move) before relying on the strain-rate limit.

Safety: a target strain is checked (`check_strain`) before anything is sent, and the speed
set on the controllers (`set maxspeed`) keeps the closing within `max_strain_rate_per_s`. Each
reading asks both axes for their position (`get pos`); a fault flag, a move that stops short, a
move not done within eta x `eta_factor` + `eta_margin_s` (jam) and a controller that does not
answer within `reply_timeout_s` all put the pair in FAULT with one reason, the stages told to
stop; the driver never waits longer than the reply timeout per question. The driver never homes
the stages (a home run would crush the sample): home them, or set their reference, before use.
Without hardware, `devices.stage.zaber_emulator.ZaberEmulator` serves the protocol.
"""

import math
import time
from dataclasses import dataclass

import serial

from devices.limits import DeviceError, LimitError
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

SPEED_UNIT = 1.6384            # maxspeed data value per microstep/s
FLAGS = {"FS": "stalled and stopped", "FQ": "encoder error", "FD": "driver disabled",
         "FT": "excessive twist", "FE": "limit error", "FO": "overdrive limit exceeded",
         "WL": "unexpected limit trigger", "WR": "no reference position (not homed)",
         "NI": "command interrupted"}


class StageControllerError(DeviceError):
    """The controller could not be set up (no reply, a rejected command): one line."""


class _NoReply(Exception):
    pass


@dataclass(frozen=True, slots=True)
class ZaberConfig(StageLimits):
    """The Zaber stage pair: its limits (`StageLimits`, the fields before these), the stages
    and their controllers (SI; positions on the controllers in microsteps)."""

    microstep_m: float = param(0.047625e-6, "length of one microstep (Microstep Size), m",
                               1e-10, 1e-3)
    closing_speed_m_s: float = param(0.01, "total closing speed while moving, m/s", 1e-7, 1.0)
    bottom_device: int = param(1, "device number of the bottom stage in the chain", 1, 99)
    bottom_axis: int = param(1, "axis number of the bottom stage", 1, 9)
    bottom_direction: int = param(1, "+1 if the bottom stage's positive direction closes the "
                                  "gap, else -1", choices=(-1, 1))
    bottom_zero_steps: int = param(0, "bottom stage position at zero closing, microsteps")
    top_device: int = param(2, "device number of the top stage in the chain", 1, 99)
    top_axis: int = param(1, "axis number of the top stage", 1, 9)
    top_direction: int = param(1, "+1 if the top stage's positive direction closes the gap, "
                               "else -1", choices=(-1, 1))
    top_zero_steps: int = param(0, "top stage position at zero closing, microsteps")
    position_tolerance_m: float = param(2e-6, "distance at which a move counts as arrived, m",
                                        0.0, 1e-2)
    eta_factor: float = param(2.0, "a move not done within eta x this (+ eta_margin_s) is "
                              "a jam", 1.0, 100.0)
    eta_margin_s: float = param(0.5, "slack added to the jam deadline (acceleration, polling), s",
                                0.0, 60.0)
    reply_timeout_s: float = param(0.2, "longest wait for a controller's reply, s", 0.01, 10.0)
    baudrate: int = param(115200, "serial baud rate (Zaber ASCII default 115200)", 1200, 921600)

    def __post_init__(self):
        check_closing_speed(self, self.closing_speed_m_s)
        if self.bottom_direction not in (-1, 1) or self.top_direction not in (-1, 1):
            raise ValueError("bottom_direction and top_direction must be +1 or -1")
        if (self.bottom_device, self.bottom_axis) == (self.top_device, self.top_axis):
            raise ValueError("the bottom and top stages must be different axes")
        StageLimits.__post_init__(self)


@dataclass(frozen=True, slots=True)
class _Reply:
    ok: bool
    busy: bool
    flag: str
    data: str


class ZaberStages:
    """The stage port on two Zaber axes; see the module docstring.

    port: the serial port (a path such as /dev/ttyUSB0, or a pyserial URL).
    cfg: limits, stages and controller settings. Opening checks that both axes answer and
    sets their speed; `StageControllerError` (one line) if not.
    """

    def __init__(self, port: str, cfg: ZaberConfig | None = None):
        self.port = port
        self.cfg = self.limits = cfg if cfg is not None else ZaberConfig()
        try:
            self._serial = serial.serial_for_url(port, baudrate=self.cfg.baudrate,
                                                 timeout=self.cfg.reply_timeout_s,
                                                 write_timeout=self.cfg.reply_timeout_s)
        except (serial.SerialException, ValueError) as e:
            raise StageControllerError(f"cannot open the stage controller's port {port}: "
                                       f"{e}") from None
        self._t = 0.0
        self._mode, self._fault = StageMode.IDLE, ""
        self._target_m = 0.0
        self._deadline: float | None = None
        self._allowed_s = 0.0
        self._replies: list[_Reply] = []
        self._pending = StageCommand()
        self._positions = (0.0, 0.0)
        try:
            self._set_speed()
            self._measure()
        except (_NoReply, StageControllerError) as e:
            self._serial.close()
            raise StageControllerError(str(e)) from None
        self._target_m = self.closing_m

    # -- the stage port --------------------------------------------------------------------
    @property
    def time_s(self) -> float:
        return self._t

    @property
    def closing_m(self) -> float:
        return self._positions[0] + self._positions[1]

    @property
    def status(self) -> StageStatus:
        return StageStatus(self._t, self.closing_m, self._target_m, self._mode, self._fault)

    def start(self, t_s: float) -> None:
        self._t = float(t_s)

    def command(self, cmd: StageCommand) -> None:
        """Keep `cmd` for the next reading; a target outside the limits, or any target while
        in FAULT, raises `LimitError` here, before anything is sent."""
        if cmd.target_strain is not None and not (cmd.stop or cmd.reset):
            check_strain(self.limits, cmd.target_strain)
            if self._mode == StageMode.FAULT:
                raise LimitError(f"stages are in FAULT ({self._fault}); reset them first")
        self._pending = cmd

    def read(self, t_s: float) -> StageReading:
        """Send the pending command, read both positions, supervise the move (never raises
        for the controller: a failure is a FAULT with its reason)."""
        self._t = float(t_s)
        cmd, self._pending = self._pending, StageCommand()
        try:
            self._apply(cmd)
            self._measure()
            self._supervise()
        except _NoReply as e:
            self._to_fault(str(e), answering=False)
        half = self._positions
        return StageReading(t=self._t, bottom_m=half[0], top_m=half[1], mode=self._mode,
                            target_strain=self._target_m / self.cfg.sample_height_m)

    def eta_s(self, strain: float) -> float:
        return abs(strain * self.cfg.sample_height_m - self.closing_m) / self.cfg.closing_speed_m_s

    def reconfigure(self, cfg: ZaberConfig) -> None:
        """New limits and settings from the next command and reading; the new speed is sent
        to the controllers at once (no reply: FAULT)."""
        self.cfg = self.limits = cfg
        try:
            self._set_speed()
        except (_NoReply, StageControllerError) as e:
            self._to_fault(str(e), answering=isinstance(e, StageControllerError))

    def get(self, setting: str) -> tuple[str, str]:
        """A setting of both axes (`get <setting>`, e.g. "deviceid", "limit.max"), as the
        controllers answer it: (bottom, top). Nothing moves; `StageControllerError` (one line)
        for a rejected setting or no reply."""
        out = []
        for device, axis in self._axes():
            try:
                reply = self._ask(device, axis, f"get {setting}")
            except _NoReply as e:
                raise StageControllerError(str(e)) from None
            if not reply.ok:
                raise StageControllerError(f"{self._name(device, axis)} rejected "
                                           f"'get {setting}': {reply.data}")
            out.append(reply.data)
        return out[0], out[1]

    def close(self) -> None:
        """Stop a move in progress (the stages hold where they are) and release the port."""
        if not self._serial.is_open:
            return
        try:
            if self._mode == StageMode.MOVING:
                self._stop_all()
        except _NoReply:
            pass
        finally:
            self._serial.close()

    # -- supervision -----------------------------------------------------------------------
    def _apply(self, cmd: StageCommand) -> None:
        if cmd.reset and self._mode == StageMode.FAULT:
            for axis in self._axes():
                self._ask(*axis, "warnings clear")
            self._stop_all()
            self._measure()
            self._mode, self._fault, self._target_m = StageMode.IDLE, "", self.closing_m
            self._deadline = None
        if cmd.stop and self._mode != StageMode.FAULT:
            self._stop_all()
            self._measure()
            self._target_m, self._deadline = self.closing_m, None
            self._mode = StageMode.IDLE if self._mode == StageMode.IDLE else StageMode.HOLDING
        elif cmd.target_strain is not None and self._mode != StageMode.FAULT:
            target = check_strain(self.limits, cmd.target_strain)
            eta = abs(target - self.closing_m) / self.cfg.closing_speed_m_s
            self._target_m, self._mode = target, StageMode.MOVING
            self._allowed_s = eta * self.cfg.eta_factor + self.cfg.eta_margin_s
            self._deadline = self._t + self._allowed_s
            for (device, axis), steps in zip(self._axes(), self._steps(target)):
                reply = self._ask(device, axis, f"move abs {steps}")
                if not reply.ok:
                    self._to_fault(f"{self._name(device, axis)} rejected 'move abs {steps}': "
                                   f"{reply.data}")
                    return

    def _supervise(self) -> None:
        if self._mode == StageMode.FAULT:
            return
        for (device, axis), reply in zip(self._axes(), self._replies):
            if reply.flag.startswith("F"):
                meaning = FLAGS.get(reply.flag, "see the Zaber warning flags")
                self._to_fault(f"{self._name(device, axis)} reports fault {reply.flag} "
                               f"({meaning}) at closing {self.closing_m:.6f} m")
                return
        if self._mode != StageMode.MOVING:
            return
        busy = any(r.busy for r in self._replies)
        off = abs(self.closing_m - self._target_m)
        if not busy and off <= max(self.cfg.position_tolerance_m, 2 * self.cfg.microstep_m):
            self._mode, self._deadline = StageMode.HOLDING, None
        elif not busy:
            flags = " ".join(r.flag for r in self._replies if r.flag != "--")
            self._to_fault(f"stages stopped at closing {self.closing_m:.6f} m, "
                           f"{off:.2e} m short of the target {self._target_m:.6f} m"
                           + (f" (flags {flags})" if flags else ""))
        elif self._deadline is not None and self._t > self._deadline:
            self._to_fault(f"target closing {self._target_m:.6f} m not reached within "
                           f"{self._allowed_s:.3g} s (eta x {self.cfg.eta_factor:g} + "
                           f"{self.cfg.eta_margin_s:g} s): at {self.closing_m:.6f} m (jammed?)")

    def _to_fault(self, reason: str, answering: bool = True) -> None:
        self._mode, self._fault, self._deadline = StageMode.FAULT, reason, None
        try:
            self._stop_all(wait=answering)
        except _NoReply:
            pass

    # -- the protocol ----------------------------------------------------------------------
    def _axes(self) -> tuple[tuple[int, int], tuple[int, int]]:
        c = self.cfg
        return (c.bottom_device, c.bottom_axis), (c.top_device, c.top_axis)

    def _name(self, device: int, axis: int) -> str:
        which = "bottom" if (device, axis) == self._axes()[0] else "top"
        return f"{which} stage (device {device} axis {axis})"

    def _steps(self, closing_m: float) -> tuple[int, int]:
        c = self.cfg
        half = 0.5 * closing_m / c.microstep_m
        return (c.bottom_zero_steps + c.bottom_direction * round(half),
                c.top_zero_steps + c.top_direction * round(half))

    def _set_speed(self) -> None:
        steps_s = 0.5 * self.cfg.closing_speed_m_s / self.cfg.microstep_m
        value = max(1, math.floor(steps_s * SPEED_UNIT))     # down: never above the rate limit
        for device, axis in self._axes():
            reply = self._ask(device, axis, f"set maxspeed {value}")
            if not reply.ok:
                raise StageControllerError(f"{self._name(device, axis)} rejected "
                                           f"'set maxspeed {value}': {reply.data}")

    def _measure(self) -> None:
        c = self.cfg
        self._replies = [self._ask(d, a, "get pos") for d, a in self._axes()]
        pos = []
        for reply, zero, sign in zip(self._replies, (c.bottom_zero_steps, c.top_zero_steps),
                                     (c.bottom_direction, c.top_direction)):
            try:
                pos.append(sign * (int(reply.data) - zero) * c.microstep_m)
            except ValueError:
                raise _NoReply(f"unreadable position {reply.data!r} from the stage controller "
                               f"on {self.port}") from None
        self._positions = (pos[0], pos[1])

    def _stop_all(self, wait: bool = True) -> None:
        for device, axis in self._axes():
            if wait:
                self._ask(device, axis, "stop")
            else:
                self._serial.write(f"/{device} {axis} stop\n".encode("ascii"))

    def _ask(self, device: int, axis: int, command: str) -> _Reply:
        """Send one command and wait (at most ~2 x reply_timeout_s) for its reply; alerts,
        info lines and other axes' replies are skipped."""
        line = f"/{device} {axis} {command}"
        try:
            self._serial.reset_input_buffer()
            self._serial.write((line + "\n").encode("ascii"))
            deadline = time.monotonic() + self.cfg.reply_timeout_s
            while True:
                raw = self._serial.read_until(b"\n")
                if not raw.endswith(b"\n"):
                    break
                words = raw.decode("ascii", "replace").split(":", 1)[0].split()
                if len(words) >= 5 and words[0] == f"@{device:02d}" and words[1] == str(axis):
                    return _Reply(words[2] == "OK", words[3] == "BUSY", words[4],
                                  " ".join(words[5:]))
                if time.monotonic() > deadline:
                    break
        except (serial.SerialException, OSError) as e:
            raise _NoReply(f"stage controller on {self.port} failed at {line!r}: {e}") from None
        raise _NoReply(f"no reply from the stage controller on {self.port} to {line!r} within "
                       f"{self.cfg.reply_timeout_s:g} s (power, cable, device number?)")
