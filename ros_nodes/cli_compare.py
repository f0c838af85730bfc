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
from pathlib import Path

from metarig.argtypes import non_negative, positive, text
from ros_nodes.logic.comparison_run import CompareError, velocity_text
from ros_nodes.recorded_compare import compare_recording
from ros_nodes.recorded_run import POSE_SOURCES


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
    print(f"{velocity_text(s)}, energy-map correlation "
          f"{s['energy_map_correlation']:.3f}, target peak KE error "
          f"{s['target_peak_ke_rel_err']:+.1%}, max displacement error "
          f"{s['max_displacement_error_m'] * 1e3:.3f} mm, {s['lost_units']} lost units")
    print(f"wrote {Path(s['rrd']).parent} (open with: rerun {s['rrd']})")
    return 0


if __name__ == "__main__":
    raise SystemExit(compare_main())
