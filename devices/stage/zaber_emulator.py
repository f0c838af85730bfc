"""An emulated chain of Zaber stages speaking the Zaber ASCII protocol on a pseudo-terminal,
so that `devices.stage.zaber.ZaberStages` (and a user) can run without hardware.

`ZaberEmulator()` opens a pseudo-terminal (`os.openpty`, raw mode) and serves it from a thread;
`port` is the path to hand to pyserial. Each axis moves toward its target at its `maxspeed`
(speed = maxspeed / 1.6384 microsteps/s, no acceleration ramp) and holds when idle. It can be
told to jam (`jam`: stop at a position, either still BUSY as a stalled controller that keeps
trying, or IDLE with a fault flag such as FS) and to go silent (`silent = True`: it reads and
never answers, as a controller without power or with a broken cable).

Understood (one device and axis per command, no message ids, checksums ignored): `get pos`,
`get maxspeed`, `set maxspeed N`, `get limit.min`, `get limit.max`, `get deviceid` (the
`device_id` given, the same for every device; made up, not a Zaber product's), `move abs N`,
`stop`, `warnings`, `warnings clear`. Replies follow the protocol: `@01 1 OK IDLE -- 1000`, `RJ` with
BADCOMMAND, BADDATA or BADAXIS; an absent device does not answer. Notices: a stopped or
replaced move sets NI (command interrupted).

`python -m devices.stage.zaber_emulator` serves two stages (devices 1 and 2, axis 1) and prints
the port to give the driver or a lab file, until Ctrl-C.
"""

import os
import select
import sys
import threading
import time
import tty
from dataclasses import dataclass, field

SPEED_UNIT = 1.6384       # Zaber's maxspeed data value per microstep/s
FLAG_ORDER = "FWN"        # faults before warnings before notices
DEVICE_ID = 99999         # what `get deviceid` answers unless told otherwise (made up)


@dataclass
class _Axis:
    pos: float = 0.0
    target: float = 0.0
    maxspeed: int = 153600
    moving: bool = False
    flags: set[str] = field(default_factory=set)
    jam_at: float | None = None
    jam_flag: str = ""
    jam_dir: int = 1
    lo: int = 0
    hi: int = 10_000_000

    def advance(self, dt: float) -> None:
        if not self.moving or dt <= 0:
            return
        step = self.maxspeed / SPEED_UNIT * dt
        gap = self.target - self.pos
        new = self.pos + max(-step, min(step, gap))
        if self.jam_at is not None and (new - self.pos) * self.jam_dir > 0 \
                and (new - self.jam_at) * self.jam_dir > 0:
            new = max(self.pos, self.jam_at) if self.jam_dir > 0 else min(self.pos, self.jam_at)
            if self.jam_flag:              # the controller detects the stall and gives up
                self.moving = False
                self.flags.add(self.jam_flag)
        self.pos = new
        if self.moving and self.pos == self.target:
            self.moving = False

    def flag(self) -> str:
        for kind in FLAG_ORDER:
            found = sorted(f for f in self.flags if f[0] == kind)
            if found:
                return found[0]
        return "--"


class ZaberEmulator:
    """Zaber stages on a pseudo-terminal; see the module docstring.

    axes: (device, axis) of each emulated axis (a chain of devices, or one multi-axis one).
    maxspeed: each axis's maxspeed at start (Zaber units: microsteps/s x 1.6384).
    """

    def __init__(self, axes=((1, 1), (2, 1)), maxspeed: int = 153600,
                 device_id: int = DEVICE_ID):
        self._axes = {tuple(a): _Axis(maxspeed=maxspeed) for a in axes}
        self.device_id = device_id
        self.silent = False
        self.received: list[str] = []      # every command line, as received
        self._lock = threading.Lock()
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)            # no echo, no line editing: bytes pass as sent
        self.port = os.ttyname(self._slave)
        self._last = time.monotonic()
        self._running = True
        self._thread = threading.Thread(target=self._serve, name="zaber-emulator", daemon=True)
        self._thread.start()

    # -- what a test or a user sets --------------------------------------------------------
    def position(self, device: int, axis: int) -> float:
        """The axis position now, microsteps."""
        with self._lock:
            self._advance()
            return self._axes[(device, axis)].pos

    def set_position(self, device: int, axis: int, steps: int) -> None:
        with self._lock:
            a = self._axes[(device, axis)]
            a.pos = a.target = float(steps)

    def jam(self, device: int, axis: int, at_steps: float | None, flag: str = "",
            direction: int = 1) -> None:
        """Moving in `direction` (+1: increasing position), the axis cannot pass `at_steps`
        (None: free again); the other way is free. With `flag` (e.g. "FS") it stops there,
        idle, with that fault flag; without, it stays BUSY there, making no progress."""
        with self._lock:
            a = self._axes[(device, axis)]
            a.jam_at, a.jam_flag, a.jam_dir = at_steps, flag, direction

    def close(self) -> None:
        self._running = False
        self._thread.join(timeout=2.0)
        for fd in (self._master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- the protocol ----------------------------------------------------------------------
    def _serve(self) -> None:
        buf = b""
        while self._running:
            ready, _, _ = select.select([self._master], [], [], 0.02)
            if not ready:
                continue
            try:
                buf += os.read(self._master, 4096)
            except OSError:
                return
            while b"\n" in buf:
                line, buf = buf.split(b"\n", 1)
                text = line.decode("ascii", "replace").strip()
                self.received.append(text)
                if self.silent or not text.startswith("/"):
                    continue
                reply = self._handle(text)
                if reply is not None:
                    os.write(self._master, (reply + "\r\n").encode("ascii"))

    def _advance(self) -> None:
        now = time.monotonic()
        for a in self._axes.values():
            a.advance(now - self._last)
        self._last = now

    def _handle(self, text: str) -> str | None:
        words = text.split(":", 1)[0][1:].split()     # drop "/" and any checksum
        try:
            device = int(words[0])
            axis = int(words[1])
        except (IndexError, ValueError):
            return None                                 # no device addressed: nobody answers
        command = words[2:]
        if not any(d == device for d, _ in self._axes):
            return None
        with self._lock:
            self._advance()
            a = self._axes.get((device, axis))
            if a is None:
                return f"@{device:02d} 0 RJ IDLE -- BADAXIS"
            flag, data = self._do(a, command)
            status = "BUSY" if a.moving else "IDLE"
            return f"@{device:02d} {axis} {flag} {status} {a.flag()} {data}"

    def _do(self, a: _Axis, command: list[str]) -> tuple[str, str]:
        getters = {"pos": lambda: round(a.pos), "maxspeed": lambda: a.maxspeed,
                   "limit.min": lambda: a.lo, "limit.max": lambda: a.hi,
                   "deviceid": lambda: self.device_id}
        match command:
            case ["get", name] if name in getters:
                return "OK", str(getters[name]())
            case ["set", "maxspeed", value]:
                if not value.isdigit() or int(value) <= 0:
                    return "RJ", "BADDATA"
                a.maxspeed = int(value)
                return "OK", "0"
            case ["move", "abs", value]:
                try:
                    target = int(value)
                except ValueError:
                    return "RJ", "BADDATA"
                if not a.lo <= target <= a.hi or any(f[0] == "F" for f in a.flags):
                    return "RJ", "BADDATA"
                if a.moving:
                    a.flags.add("NI")
                else:
                    a.flags.discard("NI")
                a.target, a.moving = float(target), a.pos != target
                return "OK", "0"
            case ["stop"]:
                if a.moving:
                    a.flags.add("NI")
                a.moving, a.target = False, a.pos
                return "OK", "0"
            case ["warnings", *rest] if rest in ([], ["clear"]):
                shown = sorted(a.flags)
                if rest:
                    a.flags.clear()
                return "OK", " ".join([f"{len(shown):02d}", *shown])
        return "RJ", "BADCOMMAND"


def main() -> int:
    """Serve two emulated stages on a pseudo-terminal until Ctrl-C."""
    with ZaberEmulator() as emu:
        print(f"Zaber emulator (devices 1 and 2, axis 1) on {emu.port}; Ctrl-C stops it",
              flush=True)
        try:
            while True:
                select.select([], [], [], 3600)
        except KeyboardInterrupt:
            print("stopped", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
