"""`metarig track`: DIC-track every unit in a folder of images, a video, a camera file (Photron
MRAW with its CIH/CIHX, Phantom CINE, multi-page TIFF) or an MCAP recording.

A thin command line over `tracking.batch` (see there for the parallel layout).

Output (.npz, the trajectory layout of `metarig simulate`): `t` [n_t] s (k / fps); `q`
[n_t, n_units, 3] (u m, v m, theta rad) from the reference outline, NaN where lost; `qdot`
[n_t, n_units, 3] backward difference (q[k] - q[k-1]) * fps, NaN at k = 0 and next to lost
frames; `quality` [n_t, n_units] ZNCC; `lost` [n_t, n_units] bool; `complete` (False when
interrupted); `fps`.
"""

import argparse
import logging
import sys
import time
from pathlib import Path

from metarig.argtypes import non_negative, positive, text
from tracking.batch import save_tracks, track_source
from tracking.calibration import CalibrationError, load_calibration
from tracking.dic import DICConfig
from tracking.frame_sources import SourceError, open_source
from tracking.units import UnitsError, load_unit_bonds, load_unit_polygons

log = logging.getLogger("metarig.track")
_DEFAULTS = DICConfig()


def _config(args) -> DICConfig:
    return DICConfig(margin_px=args.margin_px, min_points=args.min_points,
                     zncc_lost=args.zncc_lost, zncc_reacquire=max(args.zncc_lost, 0.9)
                     if args.zncc_reacquire is None else args.zncc_reacquire,
                     search_radius_px=args.search_radius_px,
                     prefilter_sigma_px=args.prefilter_sigma_px,
                     sigma_floor_px=args.sigma_floor_px, sigma_blur_share=args.sigma_blur_share)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="metarig track", description=track_main.__doc__,
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("source", help="folder of *.png frames (name order), a video file, a camera "
                   "file (.cihx/.cih/.mraw, .cine, multi-page .tif) or an .mcap recording with "
                   "sensor_msgs/Image messages")
    p.add_argument("--units", required=True, help="JSON file with 'polygons_m' (plain units "
                   "file or a design file)")
    p.add_argument("--calibration", required=True, help="calibration JSON (fps, m_per_px, "
                   "origin_px, y_up; optional homography, rectified_size_px)")
    p.add_argument("--out", type=text("--out"), default="tracks.npz", help="output .npz")
    p.add_argument("--topic", default=None, help="MCAP image topic (default: the only one, or "
                   "the one ending in image_raw)")
    p.add_argument("--reference", default=None, help="image of the reference configuration "
                   "(default: the first frame)")
    p.add_argument("--workers", type=positive(int), default=1,
                   help="worker processes; units are split between them (each decodes every "
                   "frame, so this pays off on many cores or slow-to-track scenes)")
    p.add_argument("--threads", type=non_negative(int), default=0,
                   help="numba threads per worker (0: all cores shared out between workers)")
    p.add_argument("--max-frames", type=non_negative(int), default=0,
                   help="stop after this many (0: all)")
    p.add_argument("--block", type=positive(int), default=8, help="frames per result block")
    p.add_argument("--margin-px", type=float, default=_DEFAULTS.margin_px,
                   help="subset distance from the unit outline, px")
    p.add_argument("--min-points", type=non_negative(int), default=_DEFAULTS.min_points,
                   help="units with fewer subset pixels are not tracked")
    p.add_argument("--zncc-lost", type=float, default=_DEFAULTS.zncc_lost,
                   help="correlation below which a unit is declared lost")
    p.add_argument("--zncc-reacquire", type=float, default=None,
                   help="correlation that triggers a search / regains a lost unit "
                   "(default: max(zncc-lost, 0.9))")
    p.add_argument("--search-radius-px", type=non_negative(int),
                   default=_DEFAULTS.search_radius_px,
                   help="re-acquisition search half-width, px")
    p.add_argument("--prefilter-sigma-px", type=non_negative(float),
                   default=_DEFAULTS.prefilter_sigma_px,
                   help="Gaussian smoothing of frames before tracking, px (it band-limits the "
                        "units' edges, whose sub-pixel interpolation biases slender units)")
    p.add_argument("--sigma-floor-px", type=non_negative(float),
                   default=_DEFAULTS.sigma_floor_px,
                   help="systematic error added to every pose's standard error, px at each "
                        "subset point (measure it on your camera with a rigid-motion test)")
    p.add_argument("--sigma-blur-share", type=non_negative(float),
                   default=_DEFAULTS.sigma_blur_share,
                   help="motion blur in every pose's standard error: this share of the unit's "
                        "motion since the previous frame, px (0 for short exposures)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    return p


def track_main(argv: list[str] | None = None) -> int:
    """Track the planar pose of every unit in recorded frames by digital image correlation."""
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        calib = load_calibration(args.calibration)
        polys = load_unit_polygons(args.units)
        bonds = load_unit_bonds(args.units, polys)  # a design file's ligaments, else None
        spec = open_source(args.source, args.topic)
        cfg = _config(args)
    except (CalibrationError, UnitsError, SourceError, ValueError) as exc:
        print(f"metarig track: error: {exc}", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    try:
        traj, bad = track_source(spec, polys, calib, cfg, args.workers, args.reference,
                                args.block, args.max_frames,
                                progress=not args.quiet and sys.stderr.isatty(),
                                threads=args.threads, bonds=bonds)
    except SourceError as exc:
        print(f"metarig track: error: {exc}", file=sys.stderr)
        return 2
    dt = time.perf_counter() - t0
    n_t = traj.q.shape[0]
    out = save_tracks(Path(args.out), traj, calib.fps)
    lost_frac = float(traj.lost.mean()) if traj.lost.size else 0.0
    log.info("%d frames in %.1f s (%.1f frames/s); %.2f %% unit-frames lost, %d unusable "
             "frames -> %s", n_t, dt, n_t / max(dt, 1e-9), 100 * lost_frac,
             int(bad.sum()), out)
    if not traj.complete:
        log.warning("incomplete: interrupted after %d frames; %s holds those (complete=False)",
                    n_t, out)
        return 130
    return 0
