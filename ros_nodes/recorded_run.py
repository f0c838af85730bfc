"""A recorded run as input: its design, its camera calibration, the unit poses to use (the
recording's `/dic/poses`, DIC of its frames now, or the simulated rig's ground truth) and the
measured input, exactly as `metarig compare` and `metarig calibrate` take them."""

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ros_nodes import topics
from ros_nodes.logic.comparison_run import CompareError


def read_run_file(path: Path, what: str) -> dict:
    """A JSON file `metarig rig` wrote beside its recording; CompareError if damaged."""
    from metarig.readback import DamagedFileError, read_json

    try:
        return read_json(path, what, "restore it from a copy (`metarig rig` writes it with "
                         "the recording)")
    except DamagedFileError as exc:
        raise CompareError(str(exc)) from None


class InputError(ValueError):
    """A calibration input that cannot be used (one line)."""


POSE_SOURCES = ("auto", "dic", "track", "truth")


@dataclass(frozen=True)
class Tracked:
    """Poses used as the measurement: their trajectory, first stamp and where they came from."""

    poses: object  # metarig.trajectory.Trajectory
    t0_s: float
    source: str
    tracked_here: bool


def recorded_design(rec, run_dir: Path | None) -> dict:
    """The design document of a recording (/rig/design), else `design.json` beside it."""
    if rec.design is not None:
        return rec.design
    if run_dir is not None and (run_dir / "design.json").exists():
        return read_run_file(run_dir / "design.json", "design of the recording")
    raise CompareError(f"{rec.path}: the recording holds no design (/rig/design) and no "
                       "design.json lies beside it")


def camera_calibration_path(run_dir: Path | None, given: str | None) -> Path | None:
    """The camera calibration to track with: `given`, else the run folder's `calibration.json`."""
    if given is not None:
        return Path(given)
    if run_dir is not None and (run_dir / "calibration.json").exists():
        return run_dir / "calibration.json"
    return None


def track_recording(mcap: Path, polygons_m: np.ndarray, calibration: Path, workers: int,
                    progress: bool, dic=None, bonds=None):
    """Track every frame of the recording with the offline tracker (all cores); `dic`: a
    `tracking.dic.DICConfig` (None: the defaults, fitted to the smallest unit); `bonds`: the
    lattice's ligaments for the tracker's check of each pose against its neighbours
    (`tracking.units.design_bonds`; None: no such check)."""
    from tracking.batch import track_source
    from tracking.calibration import load_calibration
    from tracking.dic import settings_for_units
    from tracking.frame_sources import open_source

    spec = open_source(mcap, topics.IMAGE.name, kind="mcap")
    calib = load_calibration(calibration)
    dic = dic or settings_for_units(polygons_m, calib.m_per_px)
    traj, _bad = track_source(spec, polygons_m, calib, dic, workers=workers, progress=progress,
                              bonds=bonds)
    return traj


def measured_poses(rec, source: str, polygons_m: np.ndarray, calibration: Path | None,
                   workers: int, progress: bool, dic=None, design: dict | None = None) -> Tracked:
    """The measurement to compare, by `source` (auto: dic, else track, else an error);
    `design`: the design document, whose lattice gives the tracker its ligaments."""
    from metarig.polygon import area_centroids
    from tracking.calibration import CalibrationError
    from tracking.frame_sources import SourceError
    from tracking.units import UnitsError, design_bonds

    ref = area_centroids(polygons_m)
    has_dic = bool(rec.pose_messages.get(topics.POSES.name))
    if source == "auto":
        source = "dic" if has_dic else "track"
    if source in ("dic", "truth"):
        topic = topics.POSES.name if source == "dic" else topics.GROUND_TRUTH.name
        if not rec.pose_messages.get(topic):
            raise CompareError(f"{rec.path}: no poses on {topic}"
                               + (" (not a simulated-rig recording)" if source == "truth" else
                                  "; use --poses track to track the frames"))
        traj, t0 = rec.poses(topic, ref)
        return Tracked(traj, t0, topic, False)
    if rec.frame_t_s.size == 0:
        raise CompareError(f"{rec.path}: the recording holds neither poses nor camera frames")
    if calibration is None:
        raise CompareError(f"{rec.path}: tracking the frames needs a calibration "
                           "(calibration.json in the run folder, or --calibration FILE)")
    try:
        bonds = design_bonds(design, polygons_m, str(rec.path)) if design is not None else None
        traj = track_recording(rec.path, polygons_m, calibration, workers, progress, dic, bonds)
    except (SourceError, CalibrationError, UnitsError) as exc:
        raise CompareError(str(exc)) from None
    if traj.n_t == rec.frame_t_s.size:  # stamps, not k / fps: dropped frames stay honest
        from dataclasses import replace

        traj = replace(traj, t=rec.frame_t_s - rec.frame_t_s[0])
        from metarig.trajectory import Trajectory

        traj = Trajectory.from_positions(traj.t, traj.q, traj.quality, traj.lost, traj.complete,
                                         traj.sigma)
    return Tracked(traj, float(rec.frame_t_s[0]), "tracked (offline DIC)", True)


def pulse_inputs(source: Path, poses_source: str = "auto", calibration: str | None = None,
                 workers: int | None = None):
    """(scene, tracked Trajectory, frame t0 s, input (t, u) as the engine takes it, stage
    (t, closing) or None) of a run folder or .mcap: the poses and measured input exactly as
    `metarig compare` takes them."""
    import os

    from comparison.experiment import engine_input, measured_input_of
    from ros_nodes.logic import comparison_run as run
    from ros_nodes.logic.comparison_run import CompareError
    from ros_nodes.logic.recording import RecordingError, read_recording

    try:
        rec = read_recording(source)
        run_dir = source if source.is_dir() else None
        doc = recorded_design(rec, run_dir)
        scene, polygons = run.design_scene(doc, where=str(rec.path))
        tracked = measured_poses(rec, poses_source, polygons,
                                 camera_calibration_path(run_dir, calibration),
                                 workers or os.cpu_count() or 1, progress=False, design=doc)
        run.check_poses(scene, tracked.poses, where=str(rec.path), min_frames=5)
        measured = measured_input_of(scene, tracked.poses, tracked.t0_s, rec.shaker_t_s,
                                     rec.shaker_u_m, rec.stage_t_s, rec.stage_closing_m,
                                     rec.closing_speed_m_s, rec.stage_hold_s)
    except (RecordingError, CompareError) as exc:
        raise InputError(str(exc)) from None
    except ValueError as exc:
        raise InputError(f"{source}: {exc}") from None
    stage = None if measured.stage_t_s is None else (measured.stage_t_s, measured.stage_closing_m)
    return scene, tracked.poses, tracked.t0_s, engine_input(measured), stage


