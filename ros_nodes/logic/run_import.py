"""A lab's own recording turned into a run folder, exactly as `metarig rig` writes one (pure).

Inputs: the camera's frames (any `tracking.frame_sources` source: MRAW/CIHX, CINE, TIFF stack,
video, image folder), their frame rate and trigger offset (from the file where it records
them, else given), the drive signal (`comparison.daq_signal`: a CSV or TDMS channel), the
sample (scene, design file, material file) and the camera calibration. Output, in a folder
written whole or not at all (`metarig.outdir.staged_folder`):

- `recording.mcap`: `/camera/image_raw` + `/camera/camera_info` per frame, the drive signal as
  `/shaker/joint_states` (joint `shaker`, position m), `/rig/design` and `/rig/config`
  (latched, also as MCAP metadata), written by the rig's recorder (`McapRecorder`);
- `design.json` (the sample's design document), `calibration.json` (the given calibration
  with the import's frame rate), `run.json` (what was imported, the recording report).

The rig clock: the trigger at t = 0, or, when the first frame was taken before the trigger,
that frame at t = 0 (the simulation starts from rest at 0 and the recording holds no negative
times). Frame k lies at offset + k / fps on it; signal samples are placed by their time after
the trigger (`signal_trigger_s`: the trigger's time on the signal's own axis) and kept from
t = 0 to one frame period after the last frame.
"""

import itertools
import json
import logging
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ros_nodes import topics
from ros_nodes.logic.cdr import (ImageEncoder, camera_info_cdr, joint_state_cdr, restamp,
                                 string_cdr)
from ros_nodes.logic.recorder import McapRecorder
from ros_nodes.logic.sequence import DESIGN_NAME, RECORDING_NAME, SUMMARY_NAME

log = logging.getLogger("metarig.import")
CALIBRATION_NAME = "calibration.json"
SHAKER_JOINT = "shaker"  # the joint name of the rig's shaker (`ros_nodes.convert`)
TOPICS = (topics.RIG_DESIGN, topics.RIG_CONFIG, topics.IMAGE, topics.CAMERA_INFO,
          topics.SHAKER_JOINTS)
METADATA = {topics.RIG_DESIGN.name: "design", topics.RIG_CONFIG.name: "rig_config"}


class ImportRefused(ValueError):
    """An input that cannot make a run folder (one line naming it)."""


@dataclass(frozen=True)
class Timing:
    """Where the frames lie in time.

    Attributes:
        fps: frame rate, Hz.
        trigger_offset_s: time of the first frame after the trigger, s (negative: before it).
        fps_from, offset_from: "file" or "flag".
    """

    fps: float
    trigger_offset_s: float
    fps_from: str
    offset_from: str

    @property
    def shift_s(self) -> float:
        """Rig time of the trigger, s (see the module docstring)."""
        return max(0.0, -self.trigger_offset_s)

    def frame_t_s(self, k) -> np.ndarray:
        """Rig time of frame k, s."""
        return self.trigger_offset_s + self.shift_s + np.asarray(k, np.float64) / self.fps


def resolve_timing(spec, fps: float | None, trigger_offset_s: float | None) -> Timing:
    """The frame rate and trigger offset from the file's header where it records them, else
    from the flags; a flag that disagrees with the file is refused.

    Raises:
        ImportRefused: a value missing from both, or file and flag disagreeing.
    """
    from tracking.frame_sources import CAMERA_FILE_KINDS, camera_file

    cam = camera_file(spec) if spec.kind in CAMERA_FILE_KINDS else None
    file_fps = cam.fps if cam is not None else None
    if file_fps is not None and fps is not None and not math.isclose(fps, file_fps,
                                                                     rel_tol=1e-6):
        raise ImportRefused(f"--fps {fps:g} disagrees with the {file_fps:g} fps recorded in "
                            f"{cam.header}; leave --fps out")
    rate = file_fps or fps
    if rate is None:
        raise ImportRefused(f"{spec.path}: no frame rate in the file: give it with --fps HZ")
    file_offset = None
    if cam is not None and cam.first_frame is not None:
        file_offset = cam.first_frame / rate
    if file_offset is not None and trigger_offset_s is not None and \
            not math.isclose(trigger_offset_s, file_offset, abs_tol=0.5 / rate):
        raise ImportRefused(f"--trigger-offset {trigger_offset_s:g} s disagrees with the file's "
                            f"first frame {cam.first_frame} after the trigger "
                            f"({file_offset:g} s); leave --trigger-offset out")
    offset = file_offset if file_offset is not None else trigger_offset_s
    if offset is None:
        raise ImportRefused(f"{spec.path}: no trigger time in the file: give the first frame's "
                            "time after the trigger with --trigger-offset S (0: the first "
                            "frame is the trigger)")
    return Timing(float(rate), float(offset), "file" if file_fps else "flag",
                  "file" if file_offset is not None else "flag")


def check_calibration(path: str | Path, max_reprojection_px: float):
    """The camera calibration (`tracking.calibration.Calibration`) and its document.

    Raises:
        ImportRefused: unreadable, invalid, or with an overall reprojection error (as
            `metarig camera-calibrate` records it) above `max_reprojection_px`.
    """
    from tracking.calibration import CalibrationError, calibration_from_dict
    from tracking.jsonfile import read_json

    try:
        doc = read_json(path, CalibrationError, "calibration")
        calib = calibration_from_dict(doc, where=str(path))
    except CalibrationError as exc:
        raise ImportRefused(str(exc)) from None
    rms = (doc.get("reprojection_error_px") or {}).get("overall_rms")
    if isinstance(rms, (int, float)) and not rms <= max_reprojection_px:
        raise ImportRefused(f"{path}: reprojection error {rms:.3g} px RMS is above "
                            f"--max-reprojection-px {max_reprojection_px:g}: calibrate again "
                            "with sharper, more varied target views")
    return calib, doc


def design_document(scene: str | None, nx: int | None, ny: int | None, design: str | None,
                    material: str | None) -> dict:
    """The sample's design document, as the rig's camera publishes it on `/rig/design`.

    Raises:
        ImportRefused: no scene, a design file that does not fit, an unreadable material file.
    """
    from hardware_sim.specimen import NOMINAL, SpecimenConfig, build

    if design:
        try:
            doc = json.loads(Path(design).read_text())
        except (OSError, ValueError) as exc:
            raise ImportRefused(f"--design {design}: not a readable design file ({exc})") \
                from None
        scene = scene or (doc.get("scene") if isinstance(doc, dict) else None)
    if not scene:
        raise ImportRefused("say which rig scene the sample is in with --scene (e.g. "
                            "focusing-24x16); a design file from `metarig rig` names it")
    # a real sample: the simulated specimen's fabrication imperfections do not apply
    cfg = SpecimenConfig(scene=scene, imperfections=NOMINAL,
                         design_path=str(Path(design).resolve()) if design else "",
                         material_path=str(Path(material).resolve()) if material else "",
                         **({"nx": nx} if nx else {}), **({"ny": ny} if ny else {}))
    try:
        return json.loads(build(cfg).design_json())
    except (ValueError, KeyError, OSError) as exc:
        raise ImportRefused(str(exc).splitlines()[0]) from None


def qos_yaml(qos: topics.Qos) -> str:
    """A topic's offered QoS as rosbag2 writes it into a channel's metadata."""
    reliability, durability = (1 if qos.reliable else 2), (1 if qos.latched else 2)
    return (f"- history: 3\n  depth: {qos.depth}\n  reliability: {reliability}\n"
            f"  durability: {durability}\n  deadline:\n    sec: 0\n    nsec: 0\n"
            "  lifespan:\n    sec: 0\n    nsec: 0\n  liveliness: 1\n"
            "  liveliness_lease_duration:\n    sec: 0\n    nsec: 0\n"
            "  avoid_ros_namespace_conventions: false\n")


def _ns(t_s: float) -> int:
    return int(round(float(t_s) * 1e9))


def write_recording(path: Path, frames, n_frames: int | None, timing: Timing, calib,
                    signal, design: dict, config: dict, compression: str = "none",
                    progress: bool = False) -> dict:
    """Write the run's MCAP: the frames (an iterator of grey [h, w] uint8/uint16 arrays) with
    their camera info, the signal samples (`DaqSignal` on the rig clock, or None) interleaved
    in time, the design and configuration. Returns the recorder's report.

    Raises:
        ImportRefused: a frame of another size than the calibration's (or than the first),
            not grey 8/16 bit, or no frame at all.
    """
    from tqdm import tqdm

    design_text, config_text = json.dumps(design), json.dumps(config, default=str)
    sig_t = np.zeros(0) if signal is None else signal.t_s
    sig_ns = [_ns(t) for t in sig_t]
    bar = tqdm(total=n_frames, unit="frame", desc="import", disable=not progress)
    j = 0
    with McapRecorder(path, compression=compression,
                      metadata={"design": {"json": design_text},
                                "rig_config": {"json": config_text}}) as rec:
        for t in TOPICS:
            rec.add_topic(t.name, t.type, qos_yaml(t.qos))
        rec.write(topics.RIG_DESIGN.name, string_cdr(design_text), 0)
        rec.write(topics.RIG_CONFIG.name, string_cdr(config_text), 0)
        enc = info = None
        k = -1
        for k, frame in enumerate(frames):
            if enc is None:
                enc, info = _encoders(frame, calib)
            elif frame.shape != enc.shape or frame.dtype != enc.dtype:
                raise ImportRefused(f"frame {k} is {frame.dtype} {frame.shape[1]}x"
                                    f"{frame.shape[0]} px, frame 0 {enc.dtype} "
                                    f"{enc.shape[1]}x{enc.shape[0]} px")
            ns = _ns(timing.frame_t_s(k))
            while j < len(sig_ns) and sig_ns[j] <= ns:
                _write_sample(rec, sig_ns[j], signal.u_m[j])
                j += 1
            rec.write(topics.IMAGE.name, enc.encode(ns, frame), ns)
            rec.write(topics.CAMERA_INFO.name, restamp(info, ns), ns)
            bar.update(1)
        bar.close()
        if k < 0:
            raise ImportRefused("the frame source holds no frame")
        for i in range(j, len(sig_ns)):
            _write_sample(rec, sig_ns[i], signal.u_m[i])
        return rec.close()


def _encoders(frame: np.ndarray, calib) -> tuple[ImageEncoder, bytes]:
    if frame.ndim != 2 or frame.dtype not in (np.uint8, np.uint16):
        raise ImportRefused(f"frames are {frame.dtype} {frame.shape}: grey 8 or 16 bit "
                            "frames are imported")
    why = calib.size_mismatch(frame.shape)
    if why:
        raise ImportRefused(f"the calibration does not fit: {why}")
    h, w = frame.shape
    return ImageEncoder(h, w, frame.dtype), camera_info_cdr(0, w, h, calib.m_per_px)


def _write_sample(rec: McapRecorder, ns: int, u_m: float) -> None:
    rec.write(topics.SHAKER_JOINTS.name, joint_state_cdr(ns, [SHAKER_JOINT], [float(u_m)]), ns)


@dataclass(frozen=True)
class ImportRequest:
    """Everything `import_run` needs (paths as given; SI)."""

    frames: str
    out: str
    fps: float | None = None
    trigger_offset_s: float | None = None
    signal: str | None = None
    channel: str | None = None
    signal_unit: str | None = None
    time_channel: str | None = None
    time_unit: str = "s"
    signal_trigger_s: float = 0.0
    calibration: str = ""
    max_reprojection_px: float = 0.5
    scene: str | None = None
    nx: int | None = None
    ny: int | None = None
    design: str | None = None
    material: str | None = None
    compression: str = "none"


def import_run(req: ImportRequest, progress: bool = False) -> dict:
    """Check every input, then write the run folder `req.out` whole (or nothing); returns the
    `run.json` document.

    Raises:
        ImportRefused: any input that cannot be used (one line); `out` not free.
    """
    from comparison.daq_signal import SignalError, read_signal
    from metarig.outdir import OutputExistsError, check_free, staged_folder
    from tracking.frame_sources import (IMAGE_SUFFIXES, SourceError, count_frames,
                                        open_source, replay_frames)

    t_start = time.perf_counter()
    try:
        out = check_free(req.out)
        spec = open_source(req.frames, suffixes=IMAGE_SUFFIXES)
        if spec.kind == "mcap":
            raise ImportRefused(f"{req.frames}: already a recording; `metarig compare` reads it")
        timing = resolve_timing(spec, req.fps, req.trigger_offset_s)
        calib, calib_doc = check_calibration(req.calibration, req.max_reprojection_px)
        n = count_frames(spec)
        frames = (f for _, f in replay_frames(spec, timing.fps))
        first = next(frames)  # the size check before anything is written
        _encoders(first, calib)
        frames = itertools.chain([first], frames)
        design = design_document(req.scene, req.nx, req.ny, req.design, req.material)
        signal = None
        if req.signal:
            t_end = float(timing.frame_t_s((n or 1) - 1)) + 1.0 / timing.fps if n else math.inf
            lo = req.signal_trigger_s - timing.shift_s
            sig = read_signal(req.signal, req.channel, req.signal_unit, req.time_channel,
                              req.time_unit, (lo, lo + t_end))
            signal = type(sig)(sig.t_s - lo, sig.u_m, sig.source, sig.unit)
        else:
            log.warning("no --signal: the comparison takes the input from the tracked driven "
                        "units alone")
        config = {"source": "metarig import", "frames": str(Path(req.frames).resolve()),
                  "kind": spec.kind, "timing": asdict(timing),
                  "signal": None if signal is None else signal.source,
                  "signal_trigger_s": req.signal_trigger_s,
                  "plan": {"scene": design["scene"], "fps": timing.fps,
                           "design": req.design or "", "material": req.material or ""},
                  "node_parameters": {}}
        with staged_folder(out) as tmp:
            report = write_recording(tmp / RECORDING_NAME, frames, n, timing, calib, signal,
                                     design, config, req.compression, progress)
            (tmp / DESIGN_NAME).write_text(json.dumps(design))
            (tmp / CALIBRATION_NAME).write_text(json.dumps({**calib_doc, "fps": timing.fps},
                                                           indent=2) + "\n")
            report["path"] = str(out.resolve() / RECORDING_NAME)
            run = {"status": "imported", "import": config, "recording": report,
                   "frames": report["topics"][topics.IMAGE.name]["count"],
                   "signal_samples": 0 if signal is None else int(signal.t_s.size),
                   "timings_s": {"total_wall": time.perf_counter() - t_start}}
            (tmp / SUMMARY_NAME).write_text(json.dumps(run, indent=2, default=str))
    except (SourceError, SignalError, OutputExistsError) as exc:
        raise ImportRefused(str(exc)) from None
    except StopIteration:
        raise ImportRefused(f"{req.frames}: holds no frame") from None
    return run
