"""The lab file: which devices a rig has, where they are and what they may be asked (TOML).

One section per device kind and one for ROS; a section left out is the simulated device with
the default limits (and ROS the local defaults)::

    format = "metarig-lab/1"              # optional

    [shaker]
    driver = "keysight33500b"             # or "sim"
    address = "TCPIP0::192.168.1.50::inst0::INSTR"   # VISA resource
    visa_library = ""                     # pyvisa backend: "" default, "@sim" this package's
                                          # emulated 33522B, "FILE.yaml@sim", "@py", ...
    model = "33522B"                      # optional: *IDN? must name this model
    serial = ""                           # optional: ... and this serial number
    m_per_v = 0.002                       # drive calibration, and any other FuncGenConfig
    max_amplitude_m = 0.010               # or ShakerLimits field

    [stage]
    driver = "zaber"                      # or "sim"
    port = "/dev/ttyUSB0"
    device_id = 0                         # optional: Zaber `get deviceid` of both stages
    microstep_m = 0.047625e-6             # any ZaberConfig (or StageLimits) field
    max_strain = 0.05

    [camera]
    driver = "pylon"                      # or "genicam" (with cti = "PATH.cti"), or "sim"
    serial = "0815-0000"                  # or index = 0; model = "..." (optional check)
    frame_rate_hz = 500.0                 # CameraSettings fields (roi = [x, y, w, h])
    max_frame_rate_hz = 1000.0            # CameraLimits fields

    [ros]
    domain_id = 0
    discovery = "localhost"               # "localhost" (default), "subnet", "off"
    static_peers = []                     # hosts to reach beyond the discovery range

Every value is checked on reading: an unknown section or key, a wrong type, a value outside a
field's range (`metarig.fields.param` bounds) or a failed cross-check raises `LabFileError`,
one line naming the file, the section and the key. The limits are the ports' own dataclasses
(`ShakerLimits`/`FuncGenConfig`, `StageLimits`/`ZaberConfig`, `CameraSettings`/`CameraLimits`),
so the drivers check every request against exactly what the file says. Relative paths (a
`.cti`, a pyvisa-sim YAML) are relative to the lab file. This module opens no device and
imports no vendor package (`devices.connect` opens the devices a lab names).
"""

import dataclasses
import math
import tomllib
from dataclasses import dataclass
from pathlib import Path

from devices.camera.port import PIXEL_FORMATS, TRIGGERS, CameraLimits, CameraSettings, \
    check_settings
from devices.shaker.waveform import ShakerLimits
from devices.stage.port import StageLimits

FORMAT = "metarig-lab/1"
EXAMPLE = Path(__file__).with_name("lab.example.toml")
SHAKER_DRIVERS = ("sim", "keysight33500b")
STAGE_DRIVERS = ("sim", "zaber")
CAMERA_DRIVERS = ("sim", "pylon", "genicam")
DISCOVERY = ("localhost", "subnet", "off")
SECTIONS = ("shaker", "stage", "camera", "ros")
# the emulated generator of this package (devices/shaker/keysight33500b.yaml), for "@sim"
SHAKER_EMULATOR_YAML = Path(__file__).parent / "shaker" / "keysight33500b.yaml"


class LabFileError(ValueError):
    """A lab file that cannot be used; the message is one line naming the file, the section
    and the key."""


@dataclass(frozen=True, slots=True)
class ShakerSection:
    """[shaker]: the driver and what it is given.

    limits: `ShakerLimits` for "sim"; `devices.shaker.funcgen.FuncGenConfig` (the limits, the
        drive calibration m_per_v and max_volts, the generator's settings) for "keysight33500b".
    address: the VISA resource name (keysight33500b).
    visa_library: pyvisa's backend, resolved ("" default; "<yaml>@sim" for pyvisa-sim).
    model, serial: what *IDN? must report (empty: any 33500B series generator).
    """

    driver: str = "sim"
    limits: ShakerLimits = dataclasses.field(default_factory=ShakerLimits)
    address: str = ""
    visa_library: str = ""
    model: str = ""
    serial: str = ""


@dataclass(frozen=True, slots=True)
class StageSection:
    """[stage]: the driver and what it is given.

    limits: `StageLimits` for "sim"; `devices.stage.zaber.ZaberConfig` for "zaber".
    port: the serial port (a path, or a pyserial URL).
    device_id: the Zaber device id both stages must report (`get deviceid`; 0: not checked).
    """

    driver: str = "sim"
    limits: StageLimits = dataclasses.field(default_factory=StageLimits)
    port: str = ""
    device_id: int = 0


@dataclass(frozen=True, slots=True)
class CameraSection:
    """[camera]: the driver, which camera, its settings and limits.

    serial: the camera's serial number ("" picks the camera at `index`).
    model: the model name the camera must report ("" not checked).
    cti: the GenTL producer (genicam), an absolute path.
    buffers: frames the driver may hold for the host.
    """

    driver: str = "sim"
    serial: str = ""
    index: int = 0
    model: str = ""
    cti: str = ""
    buffers: int = 64
    settings: CameraSettings = dataclasses.field(default_factory=CameraSettings)
    limits: CameraLimits = dataclasses.field(default_factory=CameraLimits)


@dataclass(frozen=True, slots=True)
class RosSection:
    """[ros]: the DDS domain and how far discovery reaches (default: this machine only).

    given: whether the file has a [ros] section; without one, whoever applies the file keeps
        the environment's ROS settings (`ROS_DOMAIN_ID`, ...), discovery on this machine.
    """

    domain_id: int = 0
    discovery: str = "localhost"
    static_peers: tuple[str, ...] = ()
    given: bool = dataclasses.field(default=False, compare=False)


@dataclass(frozen=True, slots=True)
class Lab:
    """A read, checked lab file (`read_lab`)."""

    path: Path
    shaker: ShakerSection = dataclasses.field(default_factory=ShakerSection)
    stage: StageSection = dataclasses.field(default_factory=StageSection)
    camera: CameraSection = dataclasses.field(default_factory=CameraSection)
    ros: RosSection = dataclasses.field(default_factory=RosSection)


def ros_environment(ros: RosSection) -> dict[str, str]:
    """The environment variables that put ROS 2 (Jazzy) where the lab file says."""
    env = {"ROS_DOMAIN_ID": str(ros.domain_id),
           "ROS_AUTOMATIC_DISCOVERY_RANGE": ros.discovery.upper()}
    if ros.static_peers:
        env["ROS_STATIC_PEERS"] = ";".join(ros.static_peers)
    return env


# -- reading -----------------------------------------------------------------------------------
class _Where:
    """Names the place of a value in an error: `FILE: [section] key: ...`."""

    def __init__(self, path: Path, section: str):
        self.path, self.section = path, section

    def error(self, key: str | None, text: str) -> LabFileError:
        where = f"{self.path}: [{self.section}]" + (f" {key}" if key else "")
        return LabFileError(f"{where}: {text}")


def _type_name(t: type) -> str:
    return {float: "a number", int: "an integer", str: "a string", bool: "true or false"}[t]


def _scalar(w: _Where, key: str, value, t: type):
    """`value` as type `t` (an integer is accepted for a number), else a one-line error."""
    if t is float and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    if not isinstance(value, t) or (t is int and isinstance(value, bool)):
        raise w.error(key, f"expected {_type_name(t)}, got {value!r}")
    if t is float and not math.isfinite(value):
        raise w.error(key, f"must be a finite number, got {value}")
    return value


def _fields_of(cls) -> dict[str, dataclasses.Field]:
    return {f.name: f for f in dataclasses.fields(cls)}


def _build(w: _Where, cls, values: dict):
    """A `cls` (a dataclass of `param` fields) from `values`, each checked for type and the
    field's bounds and choices; the class's own cross-checks run last."""
    fields = _fields_of(cls)
    defaults = cls()
    kw = {}
    for key, value in values.items():
        f = fields[key]
        value = _scalar(w, key, value, type(getattr(defaults, key)))
        m = f.metadata
        if m.get("choices") is not None and value not in m["choices"]:
            raise w.error(key, f"{value!r} is not one of {', '.join(map(str, m['choices']))}")
        if m.get("min") is not None and value < m["min"]:
            raise w.error(key, f"{value:g} is below the minimum {m['min']:g} "
                               f"({m.get('description', '')})")
        if m.get("max") is not None and value > m["max"]:
            raise w.error(key, f"{value:g} is above the maximum {m['max']:g} "
                               f"({m.get('description', '')})")
        kw[key] = value
    try:
        return cls(**kw)
    except (ValueError, TypeError) as e:
        raise w.error(None, str(e).splitlines()[0]) from None


def _unknown(w: _Where, table: dict, known: dict[str, tuple[str, ...]], driver: str) -> None:
    """Refuse a key no driver knows, or one that belongs to other drivers than `driver`.

    known: key -> the drivers it belongs to (empty: every driver)."""
    for key in table:
        if key not in known:
            raise w.error(key, f"unknown key (known: {', '.join(known)})")
        if known[key] and driver not in known[key]:
            raise w.error(key, f"only for driver {' or '.join(map(repr, known[key]))} "
                               f"(this section's driver is {driver!r})")


def _driver(w: _Where, table: dict, choices: tuple[str, ...]) -> str:
    driver = _scalar(w, "driver", table.get("driver", "sim"), str)
    if driver not in choices:
        raise w.error("driver", f"{driver!r} is not one of {', '.join(choices)}")
    return driver


def _path(base: Path, text: str) -> str:
    p = Path(text).expanduser()
    return str(p if p.is_absolute() else (base / p).resolve())


def _visa_library(w: _Where, base: Path, text: str) -> str:
    """"@sim" is this package's emulated generator; "FILE@sim" a file relative to the lab file."""
    if text == "@sim":
        return f"{SHAKER_EMULATOR_YAML}@sim"
    if text.endswith("@sim"):
        path = _path(base, text[:-4])
        if not Path(path).is_file():
            raise w.error("visa_library", f"no pyvisa-sim device file {path}")
        return f"{path}@sim"
    return text


def _shaker(w: _Where, t: dict, base: Path) -> ShakerSection:
    driver = _driver(w, t, SHAKER_DRIVERS)
    fg = ("keysight33500b",)
    own = {"driver": (), "address": fg, "visa_library": fg, "model": fg, "serial": fg}
    known = own | {k: () for k in _fields_of(ShakerLimits)}
    if driver == "keysight33500b":
        from devices.shaker.funcgen import FuncGenConfig

        cls = FuncGenConfig
        known |= {k: () for k in _fields_of(FuncGenConfig) if k not in known}
    else:
        cls = ShakerLimits
        known |= {k: fg for k in ("m_per_v", "max_volts", "sample_rate_hz", "max_points",
                                  "timeout_s")}
    _unknown(w, t, known, driver)
    text = {k: _scalar(w, k, t[k], str) for k in ("address", "visa_library", "model", "serial")
            if k in t}
    if driver == "keysight33500b" and not text.get("address", "").strip():
        raise w.error("address", "missing: the function generator's VISA resource name "
                                 "(e.g. TCPIP0::192.168.1.50::inst0::INSTR)")
    limits = _build(w, cls, {k: v for k, v in t.items() if k not in own})
    return ShakerSection(driver, limits, text.get("address", "").strip(),
                         _visa_library(w, base, text.get("visa_library", "").strip()),
                         text.get("model", ""), text.get("serial", ""))


def _stage(w: _Where, t: dict) -> StageSection:
    driver = _driver(w, t, STAGE_DRIVERS)
    own = {"driver": (), "port": ("zaber",), "device_id": ("zaber",)}
    known = own | {k: () for k in _fields_of(StageLimits)}
    if driver == "zaber":
        from devices.stage.zaber import ZaberConfig

        cls = ZaberConfig
        known |= {k: () for k in _fields_of(ZaberConfig) if k not in known}
    else:
        cls = StageLimits
    _unknown(w, t, known, driver)
    port = _scalar(w, "port", t.get("port", ""), str).strip()
    if driver == "zaber" and not port:
        raise w.error("port", "missing: the stage controller's serial port (e.g. /dev/ttyUSB0)")
    device_id = _scalar(w, "device_id", t.get("device_id", 0), int)
    if device_id < 0:
        raise w.error("device_id", f"must be >= 0 (0: not checked), got {device_id}")
    limits = _build(w, cls, {k: v for k, v in t.items() if k not in own})
    return StageSection(driver, limits, port, device_id)


def _int_list(w: _Where, key: str, value, n: int, lo: int) -> tuple[int, ...]:
    if not isinstance(value, list) or len(value) != n or \
            not all(isinstance(v, int) and not isinstance(v, bool) for v in value):
        raise w.error(key, f"expected a list of {n} integers, got {value!r}")
    if any(v < lo for v in value):
        raise w.error(key, f"every value must be >= {lo}, got {value!r}")
    return tuple(value)


def _camera(w: _Where, t: dict, base: Path) -> CameraSection:
    driver = _driver(w, t, CAMERA_DRIVERS)
    real = ("pylon", "genicam")                       # keys for a real camera, either driver
    settings_keys = ("frame_rate_hz", "exposure_s", "roi", "pixel_format", "trigger",
                     "hardware_line")
    limit_keys = ("max_frame_rate_hz", "exposure_range_s", "pixel_formats", "sensor_size_px")
    known = {"driver": (), "serial": real, "index": real, "model": real, "buffers": real,
             "cti": ("genicam",)} | {k: real for k in settings_keys + limit_keys}
    _unknown(w, t, known, driver)
    s, lim = {}, {}
    if "frame_rate_hz" in t:
        s["frame_rate_hz"] = _scalar(w, "frame_rate_hz", t["frame_rate_hz"], float)
    if "exposure_s" in t:
        s["exposure_s"] = _scalar(w, "exposure_s", t["exposure_s"], float)
    if "roi" in t:
        s["roi"] = _int_list(w, "roi", t["roi"], 4, 0)
    for key, choices in (("pixel_format", PIXEL_FORMATS), ("trigger", TRIGGERS)):
        if key in t:
            s[key] = _scalar(w, key, t[key], str)
            if s[key] not in choices:
                raise w.error(key, f"{s[key]!r} is not one of {', '.join(choices)}")
    if "hardware_line" in t:
        s["hardware_line"] = _scalar(w, "hardware_line", t["hardware_line"], str)
    if "max_frame_rate_hz" in t:
        lim["max_frame_rate_hz"] = _scalar(w, "max_frame_rate_hz", t["max_frame_rate_hz"], float)
        if lim["max_frame_rate_hz"] <= 0:
            raise w.error("max_frame_rate_hz", "must be positive")
    if "exposure_range_s" in t:
        v = t["exposure_range_s"]
        if not isinstance(v, list) or len(v) != 2:
            raise w.error("exposure_range_s", f"expected [shortest, longest] in s, got {v!r}")
        lo, hi = (_scalar(w, "exposure_range_s", x, float) for x in v)
        if not 0 < lo <= hi:
            raise w.error("exposure_range_s", f"needs 0 < shortest <= longest, got {v!r}")
        lim["exposure_range_s"] = (lo, hi)
    if "pixel_formats" in t:
        v = t["pixel_formats"]
        if not isinstance(v, list) or not v or any(x not in PIXEL_FORMATS for x in v):
            raise w.error("pixel_formats", f"expected a list of {', '.join(PIXEL_FORMATS)}, "
                                           f"got {v!r}")
        lim["pixel_formats"] = tuple(v)
    if "sensor_size_px" in t:
        lim["sensor_size_px"] = _int_list(w, "sensor_size_px", t["sensor_size_px"], 2, 1)
    settings, limits = CameraSettings(**s), CameraLimits(**lim)
    try:
        check_settings(settings, limits)
    except ValueError as e:
        raise w.error(None, str(e)) from None
    serial = t.get("serial", "")
    if isinstance(serial, int) and not isinstance(serial, bool):
        serial = str(serial)                          # serial = 1 and serial = "1" alike
    serial = _scalar(w, "serial", serial, str)
    index = _scalar(w, "index", t.get("index", 0), int)
    if index < 0:
        raise w.error("index", f"must be >= 0, got {index}")
    if serial and "index" in t:
        raise w.error("index", "give serial or index, not both")
    buffers = _scalar(w, "buffers", t.get("buffers", 64), int)
    if not 1 <= buffers <= 100_000:
        raise w.error("buffers", f"must be in 1..100000, got {buffers}")
    cti = ""
    if driver == "genicam":
        text = _scalar(w, "cti", t.get("cti", ""), str).strip()
        if not text:
            raise w.error("cti", "missing: the GenTL producer (.cti) of the camera")
        cti = _path(base, text)
    return CameraSection(driver, serial, index, _scalar(w, "model", t.get("model", ""), str),
                         cti, buffers, settings, limits)


def _ros(w: _Where, t: dict) -> RosSection:
    _unknown(w, t, {"domain_id": (), "discovery": (), "static_peers": ()}, "")
    domain = _scalar(w, "domain_id", t.get("domain_id", 0), int)
    if not 0 <= domain <= 232:
        raise w.error("domain_id", f"must be in 0..232, got {domain}")
    discovery = _scalar(w, "discovery", t.get("discovery", "localhost"), str)
    if discovery not in DISCOVERY:
        raise w.error("discovery", f"{discovery!r} is not one of {', '.join(DISCOVERY)}")
    peers = t.get("static_peers", [])
    if not isinstance(peers, list) or not all(isinstance(p, str) and p for p in peers):
        raise w.error("static_peers", f"expected a list of host names, got {peers!r}")
    return RosSection(domain, discovery, tuple(peers), given=True)


def parse_lab(doc: dict, path: Path) -> Lab:
    """A `Lab` from a parsed TOML document (`path` names it in errors and anchors relative
    paths); raises `LabFileError`."""
    base = path.parent
    for key, value in doc.items():
        if key == "format":
            if value != FORMAT:
                raise LabFileError(f"{path}: format: expected {FORMAT!r}, got {value!r}")
        elif key not in SECTIONS:
            raise LabFileError(f"{path}: {key}: unknown section (known: {', '.join(SECTIONS)})")
        elif not isinstance(value, dict):
            raise LabFileError(f"{path}: {key}: must be a section ([{key}]), got {value!r}")
    sections = {name: doc.get(name, {}) for name in SECTIONS}
    return Lab(path=path,
               shaker=_shaker(_Where(path, "shaker"), sections["shaker"], base),
               stage=_stage(_Where(path, "stage"), sections["stage"]),
               camera=_camera(_Where(path, "camera"), sections["camera"], base),
               ros=_ros(_Where(path, "ros"), sections["ros"]) if "ros" in doc else RosSection())


def read_lab(path: str | Path) -> Lab:
    """Read and check a lab file; raises `LabFileError` (one line) on any problem."""
    path = Path(path)
    try:
        with path.open("rb") as f:
            doc = tomllib.load(f)
    except FileNotFoundError:
        raise LabFileError(f"{path}: no such lab file") from None
    except IsADirectoryError:
        raise LabFileError(f"{path}: is a folder, not a lab file") from None
    except tomllib.TOMLDecodeError as e:
        raise LabFileError(f"{path}: not valid TOML: {str(e).splitlines()[0]}") from None
    except (OSError, UnicodeDecodeError) as e:
        raise LabFileError(f"{path}: cannot read: {getattr(e, 'strerror', None) or e}") from None
    return parse_lab(doc, path)
