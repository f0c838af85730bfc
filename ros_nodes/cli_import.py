"""`metarig import FRAMES --calibration FILE [--signal FILE --channel NAME] --out DIR`: a lab's
own high-speed recording as a run folder that `metarig compare` and `metarig calibrate` read.

FRAMES: a Photron recording (its `.cihx`, `.cih` or `.mraw`, the other beside it), a Phantom
`.cine`, a multi-page `.tif`, a video, or a folder of images (name order). The frame rate and
the trigger offset come from the file where it records them (MRAW, CINE; a TIFF stack from
ImageJ's frame interval), else from `--fps` / `--trigger-offset`. The drive signal is one
channel of a CSV or TDMS file. See `ros_nodes.logic.run_import` for the folder and its clock.
"""

import argparse
import logging
import sys

from metarig.argtypes import positive, text
from comparison.daq_signal import LENGTH_UNITS, TIME_UNITS


def _number(value: str) -> float:
    import math

    try:
        v = float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {value!r}") from None
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"must be finite, got {value}")
    return v


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="metarig import", description=import_main.__doc__,
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("frames", help="the camera's frames: .cihx/.cih/.mraw (Photron), .cine "
                   "(Phantom), a multi-page .tif, a video, or a folder of images (name order)")
    p.add_argument("--out", type=text("--out"), required=True,
                   help="run folder to write (must not exist, or be empty)")
    p.add_argument("--calibration", type=text("--calibration"), required=True,
                   help="camera calibration JSON (`metarig camera-calibrate`, or written by "
                   "hand: m_per_px, origin_px, y_up)")
    p.add_argument("--max-reprojection-px", type=positive(float), default=0.5,
                   help="refuse a calibration whose overall RMS reprojection error is above "
                   "this, px")
    g = p.add_argument_group("time")
    g.add_argument("--fps", type=positive(float), default=None,
                   help="frame rate, Hz (only where the file does not record it)")
    g.add_argument("--trigger-offset", type=_number, default=None, metavar="S",
                   help="time of the first frame after the trigger, s; negative when it was "
                   "taken before (only where the file does not record it; 0: the first frame "
                   "is the trigger)")
    g = p.add_argument_group("drive signal")
    g.add_argument("--signal", type=text("--signal"), default=None,
                   help="the measured drive displacement: a .csv table or a .tdms file "
                   "(without it, the input is the tracked driven units alone)")
    g.add_argument("--channel", type=text("--channel"), default=None,
                   help="its column (CSV) or GROUP/CHANNEL (TDMS); default: a CSV's second of "
                   "two columns, a TDMS file's only channel")
    g.add_argument("--signal-unit", choices=sorted(LENGTH_UNITS), default=None,
                   help="unit of the values (default: from the file: a CSV header 'x (mm)', a "
                   "TDMS unit_string)")
    g.add_argument("--time-channel", type=text("--time-channel"), default=None,
                   help="CSV time column (default: the first) or TDMS time channel (default: "
                   "the channel's waveform timing, wf_increment)")
    g.add_argument("--time-unit", choices=sorted(TIME_UNITS), default="s",
                   help="unit of the time column (a CSV header 'time (ms)' says it too)")
    g.add_argument("--signal-trigger", type=_number, default=0.0, metavar="S",
                   help="time of the trigger on the signal's own time axis, s")
    g = p.add_argument_group("sample")
    g.add_argument("--scene", type=text("--scene"), default=None,
                   help="rig scene of the sample (which units are driven or clamped), e.g. "
                   "focusing-24x16 (default: the design file's)")
    g.add_argument("--design", type=text("--design"), default=None,
                   help="design file of the sample (metarig-design/1; default: the scene's "
                   "periodic design)")
    g.add_argument("--nx", type=positive(int), default=None,
                   help="units along x of a periodic design (default: the scene's)")
    g.add_argument("--ny", type=positive(int), default=None,
                   help="units along y of a periodic design (default: the scene's)")
    g.add_argument("--material", type=text("--material"), default=None,
                   help="material file of the sample (metarig-material/1; default: the "
                   "default material)")
    p.add_argument("--compression", choices=("none", "lz4", "zstd"), default="none",
                   help="MCAP chunk compression")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    return p


def import_main(argv: list[str] | None = None) -> int:
    """Turn a lab's own camera files and drive signal into a run folder."""
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    from ros_nodes.logic.run_import import ImportRefused, ImportRequest, import_run

    req = ImportRequest(
        frames=args.frames, out=args.out, fps=args.fps, trigger_offset_s=args.trigger_offset,
        signal=args.signal, channel=args.channel, signal_unit=args.signal_unit,
        time_channel=args.time_channel, time_unit=args.time_unit,
        signal_trigger_s=args.signal_trigger, calibration=args.calibration,
        max_reprojection_px=args.max_reprojection_px, scene=args.scene, nx=args.nx,
        ny=args.ny, design=args.design, material=args.material,
        compression=args.compression)
    try:
        run = import_run(req, progress=not args.quiet and sys.stderr.isatty())
    except ImportRefused as exc:
        print(f"metarig import: error: {str(exc).splitlines()[0]}", file=sys.stderr)
        return 2
    t = run["import"]["timing"]
    print(f"imported {run['frames']} frames at {t['fps']:g} fps (first frame "
          f"{t['trigger_offset_s']:+.6g} s after the trigger) and {run['signal_samples']} "
          f"signal samples in {run['timings_s']['total_wall']:.1f} s; wrote {args.out} "
          f"(compare with: metarig compare {args.out})")
    return 0


if __name__ == "__main__":
    raise SystemExit(import_main())
