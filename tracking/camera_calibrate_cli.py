"""`metarig camera-calibrate`: a camera calibration for `metarig track` from target photographs.

Reads several views of a ChArUco or chessboard target, fits the camera (intrinsics, lens
distortion), takes the sample plane from one view of the target lying on it, and writes the
calibration JSON (see `tracking.calibration`) with the camera model, the reprojection errors
and the board, plus a contact sheet of the detected corners next to it (`<out>_corners.png`).
"""

import argparse
import json
import logging
import sys
from pathlib import Path

import cv2
import numpy as np

from metarig.argtypes import positive, text
from tracking.calibration import CalibrationError, calibration_from_dict
from tracking.camera_calibration import (
    CameraCalibrationError,
    calibrate,
    calibration_json,
    contact_sheet,
    detect,
    parse_board,
    sample_plane,
)

log = logging.getLogger("metarig.camera_calibrate")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="metarig camera-calibrate", description=camera_calibrate_main.__doc__,
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("images", nargs="+", help="views of the target (PNG, JPEG, TIFF...), "
                   "tilted every way and filling the frame between them")
    p.add_argument("--board", required=True, help="target: 'charuco:squares=11x8,square=0.015,"
                   "marker=0.011,dict=DICT_5X5_100' or 'chessboard:inner=9x6,square=0.02' (m)")
    p.add_argument("--out", type=text("--out"), default="calibration.json",
                   help="calibration JSON to write")
    p.add_argument("--plane", default=None, help="view of the target lying on the sample plane "
                   "(default: the first image); it sets the square-on grid and the sample frame")
    p.add_argument("--fps", type=positive(float), default=None,
                   help="camera frame rate written to the calibration, 1/s (default 1, with a "
                   "warning)")
    p.add_argument("--m-per-px", type=positive(float), default=None,
                   help="scale of the square-on grid, m per px (default: the camera's own "
                   "resolution over the target in the plane view)")
    p.add_argument("--max-error-px", type=positive(float), default=0.5,
                   help="refuse when the overall RMS reprojection error exceeds this, px")
    p.add_argument("--min-views", type=positive(int), default=3,
                   help="refuse with fewer views in which the target is found")
    p.add_argument("--min-corners", type=positive(int), default=8,
                   help="a view counts when at least this many corners are found")
    p.add_argument("--fit-k3", action="store_true",
                   help="also fit the 6th-order radial term k3 (wide-angle lenses; needs views "
                   "reaching the frame corners)")
    return p


def _read(path: str) -> np.ndarray:
    if not Path(path).is_file():
        raise CameraCalibrationError(f"no such image file: {path}")
    img = cv2.imread(path, cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise CameraCalibrationError(f"cannot read image {path} (not an image OpenCV reads)")
    if img.dtype != np.uint8:  # 16-bit files: detection wants 8 bit
        img = cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    return img


def _run(args) -> int:
    board = parse_board(args.board)
    names = list(args.images)
    images = [_read(n) for n in names]
    size = images[0].shape[::-1]
    for n, im in zip(names, images):
        if im.shape[::-1] != size:
            raise CameraCalibrationError(f"{n} is {im.shape[1]}x{im.shape[0]} px, the first "
                                         f"image {size[0]}x{size[1]}: one camera, one size")
    dets = [detect(board, im, args.min_corners) for im in images]
    for n, d in zip(names, dets):
        log.info("%s: %s", n, "target not found" if d is None else f"{len(d.ids)} corners")
    found = [i for i, d in enumerate(dets) if d is not None]
    out = Path(args.out)
    sheet_path = out.with_name(out.stem + "_corners.png")
    labels = [Path(n).name + (": target not found" if d is None else f": {len(d.ids)} corners")
              for n, d in zip(names, dets)]
    if len(found) < args.min_views:
        _write_sheet(sheet_path, images, dets, labels)
        raise CameraCalibrationError(
            f"target found in {len(found)} of {len(names)} views, at least {args.min_views} "
            f"needed (see {sheet_path})")
    cam = calibrate([dets[i] for i in found], size, args.fit_k3)
    for i, e in zip(found, cam.view_rms_px):
        labels[i] += f", {e:.3f} px RMS"
    _write_sheet(sheet_path, images, dets, labels)
    if not cam.rms_px <= args.max_error_px:
        worst = found[int(np.argmax(cam.view_rms_px))]
        raise CameraCalibrationError(
            f"reprojection error {cam.rms_px:.3f} px RMS exceeds --max-error-px "
            f"{args.max_error_px:g} (worst view {names[worst]}, "
            f"{cam.view_rms_px.max():.3f} px; see {sheet_path})")
    if args.plane is None:
        plane_name, plane_det = names[found[0]], dets[found[0]]
        if found[0] != 0:
            log.warning("target not found in %s: the sample plane is taken from %s",
                        names[0], plane_name)
    elif args.plane in names:
        plane_name, plane_det = args.plane, dets[names.index(args.plane)]
    else:
        plane_name, plane_img = args.plane, _read(args.plane)
        if plane_img.shape[::-1] != size:
            raise CameraCalibrationError(f"plane view {args.plane} is not {size[0]}x{size[1]} px")
        plane_det = detect(board, plane_img, args.min_corners)
    if plane_det is None:
        raise CameraCalibrationError(f"target not found in the plane view {plane_name}")
    plane = sample_plane(board, cam, plane_det, args.m_per_px)
    if args.fps is None:
        log.warning("no --fps: fps = 1 written (frame k at t = k s); set the camera's rate")
    doc = calibration_json(board, cam, plane, args.fps or 1.0,
                           [names[i] for i in found], plane_name)
    try:
        calibration_from_dict(doc, str(out))  # what `metarig track` will accept
    except CalibrationError as exc:
        raise CameraCalibrationError(str(exc)) from None
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".part")
    tmp.write_text(json.dumps(doc, indent=2) + "\n")
    tmp.replace(out)
    k = cam.camera_matrix
    log.info("%d views: fx %.2f fy %.2f cx %.2f cy %.2f px, dist %s; reprojection %.3f px RMS "
             "(worst view %.3f)", len(found), k[0, 0], k[1, 1], k[0, 2], k[1, 2],
             np.array2string(cam.dist_coeffs, precision=5), cam.rms_px, cam.view_rms_px.max())
    log.info("sample plane from %s: %.6g m/px, grid %dx%d px, origin (%.1f, %.1f) px -> %s, %s",
             plane_name, plane.m_per_px, *plane.size_px, *plane.origin_px, out, sheet_path)
    return 0


def _write_sheet(path: Path, images, dets, labels) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), contact_sheet(images, dets, labels)):
        log.warning("could not write %s", path)


def camera_calibrate_main(argv: list[str] | None = None) -> int:
    """Fit a camera and the sample plane from photographs of a calibration target."""
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        return _run(args)
    except CameraCalibrationError as exc:
        print(f"metarig camera-calibrate: error: {exc}", file=sys.stderr)
        return 2
