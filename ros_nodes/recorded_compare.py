"""A recorded experiment compared with the simulation of its measured input, offline: the
pipeline behind `metarig compare` and the comparison step of `metarig rig`.

`compare_recording` reads a rig recording, takes the tracked poses (the recording's `/dic/poses`,
or tracks its frames now, or the simulated rig's ground truth), runs the engine on exactly the
measured input (`comparison.experiment`) and writes the run-folder files: `summary.json`,
`comparison.rrd`, the PNG plots, `tracks.npz`, `simulated.npz` and `recording.mcap` with the
comparison topics. Every refusal is a `CompareError` with one line.
"""

import logging
import time
from pathlib import Path

import numpy as np

from metarig.cores import usable_cores
from ros_nodes import topics
from ros_nodes.logic.comparison_run import CompareError
from ros_nodes.recorded_run import (Tracked, camera_calibration_path, measured_poses,
                                    read_run_file, recorded_design)

log = logging.getLogger("metarig.compare")


def _frames(mcap: Path, stamps_s: np.ndarray) -> np.ndarray | None:
    """The camera frames at the given stamps, [n, H, W], or None if they do not all exist."""
    from tracking.frame_sources import SourceError, open_source, replay_frames

    try:
        spec = open_source(mcap, topics.IMAGE.name, kind="mcap")
        got = {}
        first = None
        for t_rel, frame in replay_frames(spec, fps=1.0):
            got[t_rel] = frame
            first = frame if first is None else first
    except SourceError:
        return None
    if not got:
        return None
    rel = np.array(sorted(got))
    t_abs = stamps_s - stamps_s[0]
    idx = np.searchsorted(rel, np.round(t_abs * 1e9).astype(np.int64))
    if np.any(idx >= rel.size):
        return None
    return np.stack([got[rel[i]] for i in idx])


def compare_recording(source: str | Path, out: Path | None = None, poses: str = "auto",
                      calibration: str | None = None, workers: int | None = None,
                      progress: bool = False, dic=None) -> dict:
    """Compare one recording with its simulation and write the run folder; returns the summary.

    Raises:
        CompareError: anything about the inputs that makes a comparison impossible.
    """
    from ros_nodes.logic import comparison_run as run
    from ros_nodes.logic.recording import RecordingError, read_recording

    t_start = time.perf_counter()
    try:
        rec = read_recording(source)
    except RecordingError as exc:
        raise CompareError(str(exc)) from None
    run_dir = Path(source) if Path(source).is_dir() else None
    out = Path(out) if out is not None else (run_dir or rec.path.parent)
    doc = recorded_design(rec, run_dir)
    _calibration(out, rec)  # a damaged calibration.json is refused before any work
    scene, polygons = run.design_scene(doc, where=str(rec.path))
    tracked = measured_poses(rec, poses, polygons, camera_calibration_path(run_dir, calibration),
                             workers or usable_cores(), progress, dic, design=doc)
    run.check_poses(scene, tracked.poses, where=str(rec.path), lost_hint=(
        " (small units in pixels? try --margin-px 1.5 --min-points 16)"
        if tracked.tracked_here else ""))
    t_sim = time.perf_counter()
    ec = run.simulate_and_compare(scene, tracked.poses, tracked.t0_s, rec.shaker_t_s,
                                  rec.shaker_u_m, rec.stage_t_s, rec.stage_closing_m,
                                  rec.closing_speed_m_s, rec.stage_hold_s, where=str(rec.path))
    sim_s = time.perf_counter() - t_sim
    summary = run.summary_of(ec, scene, tracked.source, str(rec.path))
    write_outputs(out, rec, scene, polygons, tracked, ec, summary)
    summary["timings_s"] = {"simulation": sim_s, "total": time.perf_counter() - t_start}
    run.write_summary(out, summary)
    return summary


def write_outputs(out: Path, rec, scene, polygons: np.ndarray, tracked: Tracked, ec,
                  summary: dict) -> None:
    """The run folder's comparison files (see the module docstring)."""
    from ros_nodes.logic.comparison_run import write_run_files

    calib = _calibration(out, rec)
    frames = _frames(rec.path, tracked.t0_s + ec.measured.t) if calib is not None else None
    rrd = write_run_files(out, scene, polygons, tracked.poses, ec, frames, calib)
    mcap = out / "recording.mcap"
    write_mcap(rec.path, mcap, tracked, ec, summary, polygons)
    summary["mcap"], summary["rrd"] = str(mcap), str(rrd)


def _calibration(out: Path, rec) -> dict | None:
    for folder in (out, rec.path.parent):
        f = folder / "calibration.json"
        if f.exists():
            return read_run_file(f, "camera calibration")
    return None


def write_mcap(src: Path, dst: Path, tracked: Tracked, ec, summary: dict,
               polygons: np.ndarray) -> Path:
    """The recording plus the comparison topics (and the offline-tracked poses)."""
    from metarig.polygon import area_centroids
    from ros_nodes import convert
    from ros_nodes.logic.comparison_run import frame_stamps_ns
    from ros_nodes.logic.mcap_append import NewMessage, append_messages

    ref = area_centroids(polygons)
    types = {topics.COMPARE_RESULT.name: topics.COMPARE_RESULT.type,
             topics.COMPARE_SUMMARY.name: topics.COMPARE_SUMMARY.type,
             topics.COMPARE_SIMULATED.name: topics.COMPARE_SIMULATED.type}
    msgs = [NewMessage(topic, ns, convert.serialize(msg))
            for topic, ns, msg in convert.comparison_messages(ec, summary, ref)]
    t_ns = frame_stamps_ns(ec)
    if tracked.tracked_here:
        types[topics.POSES.name] = topics.POSES.type
        p = tracked.poses
        for k, ns in enumerate(t_ns):
            msgs.append(NewMessage(topics.POSES.name, int(ns), convert.serialize(
                convert.unit_poses(int(ns), p.q[k], ref, p.quality[k], p.lost[k],
                                   sigma=None if p.sigma is None else p.sigma[k]))))
    from ros_nodes.logic.rerun_frames import PREVIEW_TYPE, preview_messages

    previews = preview_messages(src, topics.IMAGE.name, level=0)  # Rerun shows mono8 as depth
    if previews:
        types[topics.IMAGE_PREVIEW.name] = PREVIEW_TYPE
        msgs.extend(previews)
    replace = tuple(types)  # our own topics (a re-run replaces them); /diagnostics is shared
    types[topics.DIAGNOSTICS.name] = topics.DIAGNOSTICS.type
    return append_messages(src, dst, types, msgs, replace=replace)
