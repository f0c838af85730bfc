"""A shaker driven through a function generator: the shaker port
(`devices.shaker.port.ShakerDrive`) for a Keysight 33500B series generator (33509B to 33522B,
and the older Agilent 33500A) over SCPI with pyvisa, its output into the shaker's power
amplifier (high-impedance input).

`play` turns an accepted `Waveform` into volts (metres / `m_per_v`, the drive calibration of
generator output to shaker displacement, amplifier gain included), refuses a peak above
`max_volts` before anything is sent (`LimitError`), uploads it as an arbitrary waveform
normalised to +-1 (`DATA:VOL:CLE`, `DATA:ARB`, `FUNC ARB`, `FUNC:ARB`, `FUNC:ARB:SRAT`,
`VOLT:OFFS 0`, `VOLT` = 2 x peak, so the output is the volts computed), arms one triggered burst
(`BURS:MODE TRIG`, `BURS:NCYC 1`, `TRIG:SOUR BUS`, `BURS:STAT 1`, `OUTP 1`) and fires `*TRG` at
the start time on the rig clock (a timer thread; the rig clock is mapped to the host's
monotonic clock at `start`). `open` checks `*IDN?`, sets the high-Z load and the instrument's
own voltage limit (`VOLT:LIM`, +-max_volts) as a second guard. After every command the driver
reads `SYST:ERR?` until "No error" and raises `InstrumentError` (one line, the instrument's
reply) if an error was queued.

Between bursts the generator holds the waveform's first point: 0 V for a pulse or a burst.
`stop` aborts and turns the output off (both are tried, whichever fails); `close` leaves it off.

A watchdog thread (while open, every `watchdog_s`) asks `SYST:ERR?`: an error the instrument
queued on its own (between commands, which each drain the queue) or a query that fails (VISA
timeout, a lost connection) cancels a pending trigger and turns the output off as far as the
instrument still answers (`ABOR`, `OUTP 0`), and sets `fault` to one line saying what happened
and whether the output is off; a later `play` clears it.

`read` has no sensor to read: a function generator only commands. It returns the commanded
motion (the waveform at t since the trigger, and its derivative); a measured motion comes
through a DAQ later.

The values go up as ASCII (`DATA:ARB name,v0,v1,...`), which pyvisa-sim can match; a binary
block would upload about 2.5 times faster on a real instrument. Emulation without hardware:
`FunctionGeneratorShaker(EMULATOR_RESOURCE, visa_library=f"{EMULATOR_YAML}@sim")`, with
`keysight33500b.yaml` (its header says what pyvisa-sim can and cannot emulate).
"""

import math
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyvisa

from devices.limits import DeviceError, LimitError
from devices.shaker.port import ShakerReading
from devices.shaker.waveform import ShakerLimits, Waveform
from metarig.fields import param

EMULATOR_YAML = Path(__file__).with_name("keysight33500b.yaml")
EMULATOR_RESOURCE = "TCPIP0::emulated-33522b::inst0::INSTR"
ARB_NAME = "METARIG"
MIN_POINTS = 8          # the 33500B's shortest arbitrary waveform
VENDORS = ("Keysight Technologies", "Agilent Technologies")


class InstrumentError(DeviceError):
    """The instrument refused a command (the message names the command and its reply), did
    not answer (VISA's reason), or is not the instrument expected."""


@dataclass(frozen=True, slots=True)
class FuncGenConfig(ShakerLimits):
    """The function-generator drive: the shaker's limits (`ShakerLimits`, the fields before
    these) and the drive's calibration and the generator's settings (SI)."""

    m_per_v: float = param(0.002, "drive calibration: shaker displacement per volt at the "
                           "generator output, amplifier gain included, m/V", 1e-7, 1.0)
    max_volts: float = param(5.0, "largest voltage the amplifier input may see, V", 0.001, 10.0)
    sample_rate_hz: float = param(100e3, "arbitrary-waveform sample rate asked for, Sa/s "
                                  "(lowered to fit max_points)", 10.0, 250e6)
    max_points: int = param(65536, "longest arbitrary waveform the generator holds, points",
                            MIN_POINTS, 16_000_000)
    timeout_s: float = param(5.0, "VISA I/O timeout, s (an upload of max_points included)",
                             0.1, 60.0)
    watchdog_s: float = param(0.5, "how often the watchdog asks the generator for errors "
                              "while it is open, s (0: no watchdog)", 0.0, 60.0)


@dataclass(frozen=True, slots=True)
class ArbUpload:
    """What goes to the generator for one waveform: values normalised to +-1, the sample rate
    (Sa/s) and the peak voltage (V, amplitude = 2 x peak Vpp at offset 0)."""

    values: np.ndarray
    sample_rate_hz: float
    peak_v: float


def arb_upload(cfg: FuncGenConfig, waveform: Waveform) -> ArbUpload:
    """Sample `waveform` for the generator (first point at t = 0, last at its end), in volts,
    checked against `max_volts`; raises `LimitError` (one line) before anything is sent."""
    n = math.floor(waveform.duration_s * cfg.sample_rate_hz) + 1
    n = int(min(max(n, MIN_POINTS), cfg.max_points))
    rate = (n - 1) / waveform.duration_s
    volts = waveform.displacement(np.arange(n) / rate) / cfg.m_per_v
    peak = float(np.max(np.abs(volts)))
    if peak > cfg.max_volts:
        raise LimitError(f"waveform peak {peak:.4g} V exceeds the drive limit {cfg.max_volts:g} V "
                         f"({waveform.amplitude_m:g} m at {cfg.m_per_v:g} m/V)")
    if peak == 0.0:
        raise LimitError("waveform is zero everywhere: nothing to play")
    return ArbUpload(volts / peak, rate, peak)


def _shown(cmd: str) -> str:
    return cmd if len(cmd) <= 60 else f"{cmd[:40]}... ({len(cmd)} chars)"


class FunctionGeneratorShaker:
    """The shaker port on a Keysight 33500B series function generator; see the module docstring.

    resource: the VISA resource name (e.g. "TCPIP0::192.168.1.50::inst0::INSTR").
    cfg: limits, drive calibration and generator settings.
    visa_library: pyvisa's backend ("" for the default, "<yaml>@sim" for pyvisa-sim); ignored
        when `resource_manager` is given.
    clock: the host clock (s) the rig clock is mapped to at `start`.
    """

    def __init__(self, resource: str, cfg: FuncGenConfig | None = None, visa_library: str = "",
                 resource_manager: pyvisa.ResourceManager | None = None, clock=time.monotonic):
        self.resource = resource
        self.cfg = self.limits = cfg if cfg is not None else FuncGenConfig()
        self._rm = resource_manager if resource_manager is not None \
            else pyvisa.ResourceManager(visa_library)
        self._clock = clock
        self._io = threading.Lock()             # the trigger timer shares the VISA session
        self._device = None
        self.identity = f"function generator {resource} (not open)"
        self.model = self.serial = ""            # from *IDN? when open
        self._offset_s = 0.0                    # rig time minus host clock
        self._t = 0.0
        self._waveform: Waveform | None = None
        self._timer: threading.Timer | None = None
        self._armed = 0                         # which play() a pending trigger belongs to
        self.started_s: float | None = None     # rig time the last *TRG was sent
        self.fault = ""                         # a failed trigger or the watchdog's finding
        self.sensor = ""                        # read() is the command: nothing is measured
        self._closing = threading.Event()
        self._watchdog: threading.Thread | None = None
        self.open()

    # -- lifecycle -------------------------------------------------------------------------
    def open(self) -> None:
        if self._device is not None:
            return
        dev = None
        try:
            dev = self._rm.open_resource(self.resource, read_termination="\n",
                                         write_termination="\n")
            dev.timeout = int(self.cfg.timeout_s * 1000)
            idn = dev.query("*IDN?").strip()
        except pyvisa.errors.VisaIOError as e:
            if dev is not None:
                dev.close()
            raise InstrumentError(f"cannot reach the function generator {self.resource}: "
                                  f"{e}") from None
        fields = [f.strip() for f in idn.split(",")]
        if len(fields) < 2 or fields[0] not in VENDORS or not fields[1].startswith("335"):
            dev.close()
            raise InstrumentError(f"{self.resource} answers *IDN? with {idn!r}: not a Keysight "
                                  "33500B series function generator")
        self._device = dev
        self.model, self.serial = fields[1], fields[2] if len(fields) > 2 else ""
        self.identity = f"{fields[0]} {fields[1]} serial {self.serial or '?'}"
        self._send("*CLS", check=False)
        self._drain_errors()
        for cmd in ("OUTP 0", "OUTP:LOAD INF", f"VOLT:LIM:HIGH {self.cfg.max_volts:.6e}",
                    f"VOLT:LIM:LOW {-self.cfg.max_volts:.6e}", "VOLT:LIM:STAT 1"):
            self._send(cmd)
        if self.cfg.watchdog_s > 0:
            self._closing.clear()
            self._watchdog = threading.Thread(target=self._watch, daemon=True,
                                              name=f"watchdog {self.resource}")
            self._watchdog.start()

    def close(self) -> None:
        if self._device is None:
            return
        self._closing.set()
        if self._watchdog is not None:
            self._watchdog.join(timeout=self.cfg.timeout_s + 1.0)
            self._watchdog = None
        try:
            self.stop()
        finally:
            with self._io:
                self._device.close()
                self._device = None

    # -- the shaker port -------------------------------------------------------------------
    @property
    def time_s(self) -> float:
        return self._t

    def start(self, t_s: float) -> None:
        self._offset_s = float(t_s) - self._clock()
        self._t = float(t_s)

    def play(self, waveform: Waveform, start_s: float) -> None:
        """Upload and arm `waveform`, trigger it at rig time `start_s` (at once if that has
        passed). Raises `LimitError` (volts) before anything is sent, `InstrumentError` if the
        generator refuses a command."""
        upload = arb_upload(self.cfg, waveform)
        self._cancel_timer()
        data = ",".join(f"{v:.5f}" for v in upload.values)
        with self._io:
            self._armed += 1                    # an older trigger under way sends nothing
            for cmd in ("ABOR", "OUTP 0", "DATA:VOL:CLE", f"DATA:ARB {ARB_NAME},{data}",
                        "FUNC ARB", f"FUNC:ARB {ARB_NAME}",
                        f"FUNC:ARB:SRAT {upload.sample_rate_hz:.8e}", "VOLT:OFFS 0",
                        f"VOLT {2.0 * upload.peak_v:.6e}", "BURS:MODE TRIG", "BURS:NCYC 1",
                        "TRIG:SOUR BUS", "BURS:STAT 1", "OUTP 1"):
                self._send(cmd)
            self._query("*OPC?")            # the upload is done before the trigger
        self._waveform, self.started_s, self.fault = waveform, None, ""
        wait = start_s - (self._clock() + self._offset_s)
        if wait <= 0.0:
            self._trigger(self._armed)
        else:
            self._timer = threading.Timer(wait, self._trigger_later, (self._armed,))
            self._timer.daemon = True
            self._timer.start()

    def stop(self) -> None:
        self._cancel_timer()
        self._waveform = None
        with self._io:
            self._armed += 1                    # a trigger already under way sends nothing
            if self._device is not None:
                self._output_off()

    def read(self, t_s: float) -> ShakerReading:
        """The commanded motion at rig time `t_s` (no sensor on a function generator): the
        waveform at t_s minus the trigger time, zero before the trigger and after the end."""
        self._t = float(t_s)
        wf, t0 = self._waveform, self.started_s
        if wf is None or t0 is None:
            return ShakerReading(self._t, 0.0, 0.0)
        return ShakerReading(self._t, float(wf.displacement(t_s - t0)),
                             float(wf.velocity(t_s - t0)))

    def reconfigure(self, cfg: FuncGenConfig) -> None:
        """New limits and calibration from the next request; the instrument's voltage limit
        follows `max_volts` at once."""
        self.cfg = self.limits = cfg
        with self._io:
            for cmd in (f"VOLT:LIM:HIGH {cfg.max_volts:.6e}", f"VOLT:LIM:LOW {-cfg.max_volts:.6e}"):
                self._send(cmd)

    # -- the watchdog ----------------------------------------------------------------------
    def _watch(self) -> None:
        """Ask for errors every `watchdog_s` while open; a finding stops the output and sets
        `fault` (polling pauses until a `play` clears it)."""
        while not self._closing.wait(self.cfg.watchdog_s):
            if self.fault:
                continue
            with self._io:
                if self._device is None:
                    return
                try:
                    errors = self._drain_errors()
                except InstrumentError as e:
                    why = str(e)
                else:
                    if not errors:
                        continue
                    why = f"{self.identity} reports {'; '.join(errors)}"
                self._fail(why)

    def _fail(self, why: str) -> None:
        """Stop everything after a fault (`_io` held): the pending trigger cancelled, the output
        off as far as the instrument answers; `fault` says which."""
        self._armed += 1
        self._cancel_timer()
        self._waveform = None
        try:
            self._output_off()
        except InstrumentError as e:
            self.fault = f"{why}; the output may still be on: {e}"
        else:
            self.fault = f"{why}; output turned off"

    def _output_off(self) -> None:
        """ABOR and OUTP 0, each tried; `InstrumentError` (the first failure) after both."""
        failed = None
        for cmd in ("ABOR", "OUTP 0"):
            try:
                self._send(cmd)
            except InstrumentError as e:
                failed = failed or e
        if failed is not None:
            raise failed

    # -- SCPI ------------------------------------------------------------------------------
    def _trigger(self, armed: int) -> None:
        with self._io:
            if armed != self._armed:            # stopped or replaced since it was armed
                return
            self._send("*TRG")
            self.started_s = self._clock() + self._offset_s

    def _trigger_later(self, armed: int) -> None:
        try:
            self._trigger(armed)
        except Exception as e:  # a timer thread has no caller to raise to: the fault says it
            with self._io:
                if self._device is not None:
                    self._fail(f"the trigger failed: {e}")
                else:
                    self.fault = f"the trigger failed: {e}"

    def _cancel_timer(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None

    def _send(self, cmd: str, check: bool = True) -> None:
        if self._device is None:
            raise RuntimeError(f"{self.identity}: open() the function generator first")
        try:
            self._device.write(cmd)
        except (pyvisa.errors.VisaIOError, pyvisa.errors.InvalidSession) as e:
            # InvalidSession: the connection was closed under us (its resource manager, at exit)
            raise InstrumentError(f"{self.identity} did not take {_shown(cmd)!r}: {e}") from None
        if check:
            errors = self._drain_errors()
            if errors:
                raise InstrumentError(f"{self.identity} refused {_shown(cmd)!r}: "
                                      f"{'; '.join(errors)}")

    def query(self, cmd: str) -> str:
        """The instrument's answer to a query (e.g. "VOLT:LIM:HIGH?"), stripped; for checks
        that change nothing. `InstrumentError` if it does not answer."""
        if self._device is None:
            raise RuntimeError(f"{self.identity}: open() the function generator first")
        with self._io:
            return self._query(cmd)

    def _query(self, cmd: str) -> str:
        try:
            return self._device.query(cmd).strip()
        except (pyvisa.errors.VisaIOError, pyvisa.errors.InvalidSession) as e:
            raise InstrumentError(f"{self.identity} did not answer {cmd!r}: {e}") from None

    def _drain_errors(self, most: int = 20) -> list[str]:
        """The queued errors (SYST:ERR? until "No error"), oldest first."""
        errors = []
        for _ in range(most):
            reply = self._query("SYST:ERR?")
            code = reply.split(",", 1)[0].strip()
            if code in ("0", "+0") or "no error" in reply.lower():
                break
            errors.append(reply)
        return errors
