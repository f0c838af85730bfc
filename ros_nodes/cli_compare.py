"""`metarig compare RUN_DIR|FILE.mcap [--out DIR]`: experiment against simulation, offline.

Reads a rig recording, takes the tracked poses (the recording's `/dic/poses`, or tracks its
frames now, or the simulated rig's ground truth), runs the engine on exactly the measured input
(`comparison.experiment`), and writes into DIR: `summary.json`, `comparison.rrd` (Rerun, with
its side-by-side blueprint), the PNG plots, `tracks.npz` and `simulated.npz` (the one
trajectory format), and `recording.mcap` = the recording plus the comparison topics
(`/compare/result`, `/compare/summary`, `/compare/simulated_poses`, `/diagnostics`, and
`/dic/poses` when tracked here). With DIR = the run folder, its MCAP is replaced atomically.
"""

import argparse
import logging
import sys
import time
from pathlib import Path

import numpy as np

from metarig.argtypes import non_negative, positive, text
from ros_nodes import topics
from ros_nodes.logic.comparison_run import SUMMARY_KEYS, CompareError  # noqa: F401 (re-export)
from ros_nodes.recorded_run import (POSE_SOURCES, Tracked, camera_calibration_path,
                                    measured_poses, read_run_file, recorded_design)

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
    import os

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
                             workers or os.cpu_count() or 1, progress, dic)
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
    from ros_nodes.logic.comparison_run import comparison_messages, frame_stamps_ns
    from ros_nodes.logic.mcap_append import NewMessage, append_messages

    ref = area_centroids(polygons)
    types = {topics.COMPARE_RESULT.name: topics.COMPARE_RESULT.type,
             topics.COMPARE_SUMMARY.name: topics.COMPARE_SUMMARY.type,
             topics.COMPARE_SIMULATED.name: topics.COMPARE_SIMULATED.type}
    msgs = [NewMessage(topic, ns, convert.serialize(msg))
            for topic, ns, msg in comparison_messages(ec, summary, ref)]
    t_ns = frame_stamps_ns(ec)
    if tracked.tracked_here:
        types[topics.POSES.name] = topics.POSES.type
        p = tracked.poses
        for k, ns in enumerate(t_ns):
            msgs.append(NewMessage(topics.POSES.name, int(ns), convert.serialize(
                convert.unit_poses(int(ns), p.q[k], ref, p.quality[k], p.lost[k]))))
    from ros_nodes.logic.rerun_frames import PREVIEW_TYPE, preview_messages

    previews = preview_messages(src, topics.IMAGE.name, level=0)  # Rerun shows mono8 as depth
    if previews:
        types[topics.IMAGE_PREVIEW.name] = PREVIEW_TYPE
        msgs.extend(previews)
    replace = tuple(types)  # our own topics (a re-run replaces them); /diagnostics is shared
    types[topics.DIAGNOSTICS.name] = topics.DIAGNOSTICS.type
    return append_messages(src, dst, types, msgs, replace=replace)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="metarig compare", description=compare_main.__doc__,
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("source", help="run folder (with one .mcap) or an .mcap recording")
    p.add_argument("--out", type=Path, default=None,
                   help="output folder (default: the run folder, or the recording's folder)")
    p.add_argument("--poses", choices=POSE_SOURCES, default="auto",
                   help="measurement: the recording's /dic/poses, track the frames now, or the "
                   "simulated rig's ground truth (auto: /dic/poses if recorded, else track)")
    p.add_argument("--calibration", type=text("--calibration"), default=None,
                   help="calibration JSON for tracking (default: calibration.json beside it)")
    p.add_argument("--workers", type=positive(int), default=None,
                   help="tracker processes (default: cores)")
    from tracking.dic import SMALL_UNIT_MARGIN_PX, SMALL_UNIT_MIN_POINTS, DICConfig

    d = DICConfig()
    p.add_argument("--margin-px", type=non_negative(float), default=None,
                   help=f"tracking: subset distance from the unit outline, px (default "
                   f"{d.margin_px}, {SMALL_UNIT_MARGIN_PX} when the smallest unit needs it)")
    p.add_argument("--min-points", type=positive(int), default=None,
                   help=f"tracking: units with fewer subset pixels are not tracked (default "
                   f"{d.min_points}, {SMALL_UNIT_MIN_POINTS} when the smallest unit needs it)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    return p


def compare_main(argv: list[str] | None = None) -> int:
    """Compare a recorded experiment with the simulation of its measured input."""
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        from dataclasses import replace

        from tracking.dic import DICConfig

        dic = None  # defaults fitted to the smallest unit, unless set here
        if args.margin_px is not None or args.min_points is not None:
            d = DICConfig()
            dic = replace(d, margin_px=d.margin_px if args.margin_px is None else args.margin_px,
                          min_points=d.min_points if args.min_points is None else
                          args.min_points)
        s = compare_recording(args.source, args.out, args.poses, args.calibration,
                              args.workers, progress=not args.quiet and sys.stderr.isatty(),
                              dic=dic)
    except CompareError as exc:
        print(f"metarig compare: error: {exc}", file=sys.stderr)
        return 2
    print(f"velocity NRMSE {s['velocity_nrmse']:.2%}, energy-map correlation "
          f"{s['energy_map_correlation']:.3f}, target peak KE error "
          f"{s['target_peak_ke_rel_err']:+.1%}, max displacement error "
          f"{s['max_displacement_error_m'] * 1e3:.3f} mm, {s['lost_units']} lost units")
    print(f"wrote {Path(s['rrd']).parent} (open with: rerun {s['rrd']})")
    return 0


if __name__ == "__main__":
    raise SystemExit(compare_main())
