"""What this machine can see of lab devices, without opening any: pylon cameras, GenTL
producers and their cameras, VISA instruments, serial ports. Each probe fails softly: a missing
library or bus gives a `Probe` with `error` (one line saying why) instead of an exception.

`GENICAM_GENTL64_PATH` lists the folders of the GenTL producers a vendor's installer put on
this machine (`os.pathsep`-separated); the emulating producer of the `genicam` wheel
(`viky.cti`) is added to them. pylon's emulated cameras appear when `PYLON_CAMEMU=N` is set
before the probe runs.
"""

import ctypes
import os
from dataclasses import dataclass
from pathlib import Path

GENTL_PATH_VAR = "GENICAM_GENTL64_PATH"


@dataclass(frozen=True, slots=True)
class Found:
    """One device: `name` is what a lab file takes to pick it (serial, resource, port)."""

    name: str
    detail: str = ""


@dataclass(frozen=True, slots=True)
class Probe:
    """What one probe saw: `kind` (e.g. "pylon", "gentl viky.cti", "visa @sim", "serial"),
    its devices, and `error` when it could not look."""

    kind: str
    found: tuple[Found, ...] = ()
    error: str = ""
    source: str = ""            # the producer file, the VISA library


def _why(e: BaseException) -> str:
    text = str(e).strip().splitlines()
    return f"{type(e).__name__}: {text[0]}" if text else type(e).__name__


def probe_pylon() -> Probe:
    """Cameras seen by pylon's transport-layer factory (emulated ones with PYLON_CAMEMU)."""
    try:
        from devices.camera.pylon import list_cameras
    except ImportError as e:
        return Probe("pylon", error=f"pypylon is not installed ({_why(e)})")
    try:
        cams = list_cameras()
    except Exception as e:  # a vendor SDK's own error types: say why, never raise
        return Probe("pylon", error=_why(e))
    return Probe("pylon", tuple(Found(c["serial"], f"{c['vendor']} {c['model']} "
                                                   f"[{c['device_class']}]") for c in cams))


def gentl_producers() -> list[Path]:
    """The `.cti` files on GENICAM_GENTL64_PATH, then the genicam wheel's own producer."""
    out: list[Path] = []
    for folder in os.environ.get(GENTL_PATH_VAR, "").split(os.pathsep):
        if folder and Path(folder).is_dir():
            out += sorted(Path(folder).glob("*.cti"))
    try:
        from devices.camera.genicam import bundled_producer
    except ImportError:
        bundled = None
    else:
        bundled = bundled_producer()
    if bundled is not None and bundled.resolve() not in {p.resolve() for p in out}:
        out.append(bundled)
    return out


def probe_gentl(cti: Path) -> Probe:
    """The cameras one GenTL producer enumerates (through harvesters)."""
    kind = f"gentl {cti.name}"
    try:
        from harvesters.core import Harvester
    except ImportError as e:
        return Probe(kind, error=f"harvesters is not installed ({_why(e)})", source=str(cti))
    try:  # harvesters skips a producer it cannot load without a word: load it first
        ctypes.CDLL(str(cti))
    except OSError as e:
        return Probe(kind, error=f"not a loadable GenTL producer: {_why(e)}", source=str(cti))
    h = Harvester()
    try:
        h.add_file(str(cti))
        h.update()
        found = tuple(Found(str(d.serial_number), f"{d.vendor} {d.model} [{d.id_}]")
                      for d in h.device_info_list)
    except Exception as e:  # a producer that fails to load or to enumerate
        return Probe(kind, error=_why(e), source=str(cti))
    finally:
        h.reset()
    return Probe(kind, found, source=str(cti))


def _visa_kind(library: str) -> str:
    if not library:
        return "visa (default library)"
    if "@" in library:
        path, backend = library.rsplit("@", 1)
        return f"visa @{backend}" + (f" {Path(path).name}" if path else "")
    return f"visa {library}"


def probe_visa(library: str = "") -> Probe:
    """The instruments a VISA library lists ("" pyvisa's default, "<yaml>@sim" pyvisa-sim)."""
    kind = _visa_kind(library)
    try:
        import pyvisa
    except ImportError as e:
        return Probe(kind, error=f"pyvisa is not installed ({_why(e)})", source=library)
    try:
        rm = pyvisa.ResourceManager(library)
    except Exception as e:  # no VISA implementation, a bad backend: why, in one line
        return Probe(kind, error=_why(e), source=library)
    try:
        names = rm.list_resources()
    except Exception as e:
        return Probe(kind, error=_why(e), source=library)
    finally:
        rm.close()
    return Probe(kind, tuple(Found(n) for n in names), source=library)


def probe_serial() -> Probe:
    """The serial ports (USB adapters, built-in UARTs; not pseudo-terminals)."""
    try:
        from serial.tools import list_ports
    except ImportError as e:
        return Probe("serial", error=f"pyserial is not installed ({_why(e)})")
    try:
        ports = list_ports.comports()
    except Exception as e:
        return Probe("serial", error=_why(e))
    return Probe("serial", tuple(Found(p.device, " ".join(x for x in (p.description, p.hwid)
                                                           if x and x != "n/a"))
                                 for p in sorted(ports, key=lambda p: p.device)))


def probe_all(visa_libraries: tuple[str, ...] = ("",)) -> list[Probe]:
    """Every probe: pylon, each GenTL producer, each VISA library, serial ports."""
    return [probe_pylon(), *(probe_gentl(p) for p in gentl_producers()),
            *(probe_visa(lib) for lib in visa_libraries), probe_serial()]
