"""Typed node configurations: one frozen dataclass per node, defaults + description + bounds.

Each field carries `metadata={"description", "min", "max", "choices"}`. Nested device configs
(`hardware_sim` dataclasses) become dotted parameter names (`device.max_amplitude_m`). This
module is pure (no rclpy): `flat_fields` lists the parameters, `from_flat` rebuilds and
validates a config from parameter values, `load_yaml` reads a ROS 2 parameter file. The rclpy
side (descriptors with ranges, the on-set callback) is `ros_nodes.nodes._params`.
"""

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from devices.shaker.compensation import CompensationConfig
from hardware_sim.shaker import ShakerConfig
from hardware_sim.specimen import Imperfections
from hardware_sim.stage import StageConfig
from metarig.fields import param
from ros_nodes.topics import IMAGE, RECORDED

SOURCES = ("sim", "mcap", "folder", "video", "pattern")
HARDWARE = ("sim", "lab")  # the simulator (or replay), or the devices of a lab file


class ConfigError(ValueError):
    """A parameter value that is out of range or inconsistent (the message says which)."""


def _check_lab_file(hardware: str, lab_file: str) -> None:
    if hardware == "lab" and not lab_file.strip():
        raise ValueError("hardware 'lab' needs lab_file (the lab file naming the devices)")


@dataclass(frozen=True, slots=True)
class ShakerNodeConfig:
    """Parameters of the shaker command node."""

    device: ShakerConfig = param(ShakerConfig, "shaker physics and safety limits")
    rate_hz: float = param(1000.0, "device step and joint-state rate (node clock), Hz",
                           1.0, 20000.0)
    command_rate_hz: float = param(2000.0, "sample rate of the published commanded waveform, Hz",
                                10.0, 100000.0)
    seed: int = param(0, "seed of the simulated sensor noise", 0, 2**31 - 1)
    compensation: CompensationConfig = param(CompensationConfig, "drive compensation "
                                             "(~/compensate): tolerances, caps, rest between "
                                             "drives")
    hardware: str = param("sim", "device backend: the simulated shaker, or the [shaker] of "
                          "lab_file (whose limits replace device.*)", choices=HARDWARE)
    lab_file: str = param("", "lab file (TOML) naming the devices, when hardware is 'lab'")
    allowed_callers: tuple[str, ...] = param(
        lambda: ("/sequencer",), "nodes whose motion requests are accepted (fully qualified "
        "names; '*': any node); refused while another node has a client on the service")
    autostart: bool = param(True, "configure and activate on start-up (the launcher drives it)")

    def __post_init__(self):
        _check_lab_file(self.hardware, self.lab_file)


@dataclass(frozen=True, slots=True)
class StageNodeConfig:
    """Parameters of the linear stage node."""

    device: StageConfig = param(StageConfig, "stage physics and safety limits")
    rate_hz: float = param(500.0, "device step and joint-state rate (node clock), Hz", 1.0, 10000.0)
    seed: int = param(1, "seed of the simulated encoder noise", 0, 2**31 - 1)
    hardware: str = param("sim", "device backend: the simulated stages, or the [stage] of "
                          "lab_file (whose limits replace device.*)", choices=HARDWARE)
    lab_file: str = param("", "lab file (TOML) naming the devices, when hardware is 'lab'")
    allowed_callers: tuple[str, ...] = param(
        lambda: ("/sequencer",), "nodes whose motion requests are accepted (fully qualified "
        "names; '*': any node); refused while another node has a client on the service")
    autostart: bool = param(True, "configure and activate on start-up (the launcher drives it)")

    def __post_init__(self):
        _check_lab_file(self.hardware, self.lab_file)


@dataclass(frozen=True, slots=True)
class CameraNodeConfig:
    """Parameters of the camera source node."""

    source: str = param("pattern", "frame source", choices=SOURCES)
    path: str = param("", "recording (.mcap), image folder or video file to replay")
    image_topic: str = param(IMAGE.name, "topic of the frames inside an MCAP replay")
    fps: float = param(1000.0, "frame rate (pattern, folder, video; sim: capture rate), Hz",
                    0.1, 100000.0)
    rate_factor: float = param(1.0, "publish speed relative to real time (0: as fast as possible)",
                            0.0, 100.0)
    width: int = param(640, "frame width (pattern, sim), px", 8, 8192)
    height: int = param(480, "frame height (pattern, sim), px", 8, 8192)
    m_per_px: float = param(6.0e-4, "image scale (sim, camera info), m/px", 1e-7, 1.0)
    n_frames: int = param(0, "frames to publish then stop (0: all / unlimited)", 0, 10**9)
    loop: bool = param(False, "restart a replay at its end")
    publish_clock: bool = param(False, "publish /clock from the frame stamps (replay)")
    frame_id: str = param("camera", "frame_id of the images")
    queue_depth: int = param(1000, "frames the image publisher keeps for slow readers (reliable "
                          "keep-last: older unacknowledged frames are dropped, and counted by "
                          "the recorder)", 1, 100000)
    scene: str = param("precompression-24x18", "sim: design_engine scene name")
    nx: int = param(24, "sim: units along x", 2, 200)
    ny: int = param(16, "sim: units along y", 2, 200)
    design_path: str = param("", "sim: design file of the sample (empty: the scene's periodic "
                             "design); its lattice sets nx, ny")
    material_path: str = param("", "sim: material file (metarig-material/1) of the sample "
                               "(empty: the default material)")
    material_si: str = param("", "sim: the sample's material as the SI values of its file, "
                             "JSON, when the caller read the file (metarig rig); then "
                             "material_path is not read again")
    perturb: float = param(0.0, "sim: relative spread of the specimen's true stiffnesses", 0.0, 0.5)
    specimen: Imperfections = param(Imperfections, "sim: how the sample differs from its model")
    noise_std: float = param(0.01, "sim: read noise, fraction of full scale", 0.0, 0.5)
    lighting_gradient: float = param(0.15, "sim: left-right lighting gradient", 0.0, 0.9)
    exposure_samples: int = param(3, "sim: sub-exposures for motion blur", 1, 16)
    capture_start_s: float = param(-1.0, "sim: simulated time the next capture starts at, s "
                                   "(-1: when `start` is called; used once). The sequencer sets "
                                   "it to the time it holds, so that a camera whose clock lags "
                                   "under load cannot start the capture early", -1.0, 1e9)
    supersample: int = param(4, "sim: sub-pixel samples per pixel side (a pixel's light "
                             "integrated on this many points squared: 2 aliases an outline's "
                             "edge into grey steps that move the tracked poses)", 1, 8)
    seed: int = param(0, "seed of noise and speckle", 0, 2**31 - 1)
    snapshot_frames: int = param(8, "frames at rest that `~/snapshot` averages into the "
                                 "reference image (the reference's read noise is in every "
                                 "tracked pose; 1: a single frame)", 1, 256)
    hardware: str = param("sim", "camera backend: the frames `source` names, or the [camera] of "
                          "lab_file (a pylon or GenICam camera; a 'sim' entry keeps `source`)",
                          choices=HARDWARE)
    lab_file: str = param("", "lab file (TOML) naming the camera, when hardware is 'lab'")
    frame_rate_hz: float = param(0.0, "lab camera: frame rate, Hz (0: the lab file's)",
                                 0.0, 1.0e6)
    exposure_s: float = param(0.0, "lab camera: exposure, s (0: the lab file's)", 0.0, 100.0)
    pixel_format: str = param("", "lab camera: pixel format (empty: the lab file's)",
                              choices=("", "mono8", "mono16"))
    trigger: str = param("", "lab camera: free, software (the node fires at the frame rate) or "
                         "hardware trigger (empty: the lab file's)",
                         choices=("", "free", "software", "hardware"))
    grab_timeout_s: float = param(2.0, "lab camera: no frame for this long while streaming is "
                                  "an error (hardware trigger: counted from the first frame), s",
                                  0.05, 3600.0)

    def __post_init__(self):
        _check_lab_file(self.hardware, self.lab_file)


@dataclass(frozen=True, slots=True)
class RecorderNodeConfig:
    """Parameters of the MCAP recorder node."""

    path: str = param("recording.mcap", "output MCAP file")
    topics: tuple[str, ...] = param(lambda: RECORDED,
                                 "topics to record (those that appear; types discovered)")
    autostart: bool = param(False, "start recording immediately instead of on ~/start")
    chunk_size: int = param(1 << 20, "MCAP chunk size, bytes (a killed writer loses <= 1 chunk)",
                         1024, 1 << 28)
    compression: str = param("none", "MCAP chunk compression", choices=("none", "lz4", "zstd"))
    queue_depth: int = param(2000, "subscription queue depth (keep-last)", 1, 100000)
    write_queue: int = param(4000, "messages waiting for the writer thread at most (more: dropped "
                          "and counted as queue_overflow)", 1, 1000000)
    gap_factor: float = param(1.5, "a stamp step above this many median periods is a gap",
                           1.01, 100.0)
    discovery_period_s: float = param(0.2, "how often new topics are looked for, s", 0.01, 10.0)


@dataclass(frozen=True, slots=True)
class ParamSpec:
    """One flat ROS parameter: name, Python type, default, description, bounds, choices."""

    name: str
    type: type
    default: Any
    description: str
    min: float | None
    max: float | None
    choices: tuple | None


def _field_type(f: dataclasses.Field, value) -> type:
    if isinstance(value, bool):
        return bool
    if isinstance(value, tuple):
        return tuple
    return type(value)


def flat_fields(cls, prefix: str = "", defaults=None) -> list[ParamSpec]:
    """The flat parameter list of a config class (nested dataclasses get dotted names, with the
    defaults the outer class gives them: `defaults`, an instance, else `cls()`)."""
    out = []
    defaults = cls() if defaults is None else defaults
    for f in dataclasses.fields(cls):
        value = getattr(defaults, f.name)
        if dataclasses.is_dataclass(value):
            out += flat_fields(type(value), f"{prefix}{f.name}.", value)
            continue
        m = f.metadata
        out.append(ParamSpec(prefix + f.name, _field_type(f, value), value,
                             m.get("description", ""), m.get("min"), m.get("max"),
                             m.get("choices")))
    return out


def to_flat(cfg, prefix: str = "") -> dict[str, Any]:
    """Config -> {dotted name: value}."""
    out = {}
    for f in dataclasses.fields(cfg):
        v = getattr(cfg, f.name)
        if dataclasses.is_dataclass(v):
            out.update(to_flat(v, f"{prefix}{f.name}."))
        else:
            out[prefix + f.name] = v
    return out


def check_value(spec: ParamSpec, value) -> Any:
    """Coerce and range-check one value; raises `ConfigError` with the reason."""
    if spec.type is float and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    if spec.type is tuple:
        if isinstance(value, str) or not all(isinstance(v, str) for v in value):
            raise ConfigError(f"{spec.name}: expected a list of strings, got {value!r}")
        value = tuple(value)
    elif not isinstance(value, spec.type) or (spec.type is int and isinstance(value, bool)):
        raise ConfigError(f"{spec.name}: expected {spec.type.__name__}, got {value!r}")
    if spec.type in (int, float):
        if spec.type is float and math.isnan(value):
            raise ConfigError(f"{spec.name}: NaN is not a valid value")
        if spec.min is not None and value < spec.min:
            raise ConfigError(f"{spec.name}={value} is below the minimum {spec.min}")
        if spec.max is not None and value > spec.max:
            raise ConfigError(f"{spec.name}={value} is above the maximum {spec.max}")
    if spec.choices is not None and value not in spec.choices:
        raise ConfigError(f"{spec.name}={value!r}: choose one of {', '.join(spec.choices)}")
    return value


def from_flat(cls, values: dict[str, Any], base=None):
    """Build a validated config of class `cls` from flat values over `base` (default: defaults).

    Raises `ConfigError` for an unknown name, a bad type, an out-of-range value or a failed
    cross-field check of a (nested) config.
    """
    specs = {s.name: s for s in flat_fields(cls)}
    flat = to_flat(base if base is not None else cls())
    for k, v in values.items():
        if k not in specs:
            raise ConfigError(f"unknown parameter {k!r}")
        flat[k] = check_value(specs[k], v)

    def build(c, prefix):
        kw = {}
        for f in dataclasses.fields(c):
            default = getattr(c(), f.name)
            if dataclasses.is_dataclass(default):
                kw[f.name] = build(type(default), f"{prefix}{f.name}.")
            else:
                kw[f.name] = flat[prefix + f.name]
        try:
            return c(**kw)
        except (ValueError, TypeError) as e:
            raise ConfigError(f"{prefix or c.__name__}: {e}") from e

    return build(cls, "")


def load_yaml(path: str | Path, node_name: str) -> dict[str, Any]:
    """Flat parameters for `node_name` from a ROS 2 parameter file (`/**` entries apply to all).

    The file layout is the standard one: `node_name: {ros__parameters: {...}}`; nested maps
    become dotted names.
    """
    try:
        doc = yaml.safe_load(Path(path).read_text()) or {}
    except (OSError, UnicodeDecodeError) as e:
        raise ConfigError(f"cannot read parameter file {path}: {e}") from e
    except yaml.YAMLError as e:  # its text spans lines: the problem and where, in one
        mark = getattr(e, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        raise ConfigError(f"cannot read parameter file {path}: not valid YAML "
                          f"({getattr(e, 'problem', None) or type(e).__name__}{where})") from e
    if not isinstance(doc, dict):
        raise ConfigError(f"cannot read parameter file {path}: not a map of node names")
    out: dict[str, Any] = {}

    def flatten(d, prefix=""):
        for k, v in d.items():
            if isinstance(v, dict):
                flatten(v, f"{prefix}{k}.")
            else:
                out[prefix + k] = tuple(v) if isinstance(v, list) else v

    for key in ("/**", node_name, "/" + node_name.lstrip("/")):
        entry = doc.get(key)
        if isinstance(entry, dict):
            flatten(entry.get("ros__parameters", {}) or {})
    return out


@dataclass(frozen=True, slots=True)
class CompareNodeConfig:
    """Parameters of the comparison node (experiment against simulation)."""

    out_dir: str = param("", "folder for summary.json, comparison.rrd and the plots "
                         "(empty: publish only)")
    auto: bool = param(True, "compare when /rig/phase reports stop or done (poses received)")
    min_frames: int = param(3, "fewer pose frames than this: refused", 3, 10**9)
