"""`metarig camera-calibrate` on ChArUco views rendered with a known camera, and tracking through
the calibration it writes (a tilted, distorted view against the square-on one)."""

import json
from dataclasses import replace

import cv2
import numpy as np
import pytest
from camera_synth import Camera, charuco_picture, look_at, project, ray_grid, view
from dic_synth import make_scene

from tracking.calibration import load_calibration
from tracking.camera_calibrate_cli import camera_calibrate_main
from tracking.camera_calibration import CameraCalibrationError, parse_board, undistort_px
from tracking.dic import DICTracker, init_state, track_frame

BOARD = "charuco:squares=11x8,square=0.015,marker=0.011,dict=DICT_5X5_100"
CAM = Camera(K=np.array([[800.0, 0.0, 322.0], [0.0, 805.0, 236.0], [0.0, 0.0, 1.0]]),
             dist=np.array([-0.12, 0.08, 0.0008, -0.0005, 0.0]), size=(640, 480))
SS = 3  # sub-pixel samples per pixel side
BLUR = 0.8  # optical blur of the lens, px
CENTRE = (0.0825, 0.06)  # board centre, m
Z0 = 0.33  # distance of the square-on view, m
# (rx, ry, rz rad, (x, y, z) m of the board centre from the camera); the first view is
# square-on, the default plane view; the others reach every corner of the frame
POSES = [(0.0, 0.0, 0.0, (0.0, 0.0, Z0)),
         (0.35, 0.0, 0.05, (-0.07, -0.05, 0.36)), (-0.35, 0.05, -0.05, (0.07, 0.05, 0.36)),
         (0.0, 0.4, 0.1, (0.07, -0.05, 0.37)), (0.05, -0.4, 0.0, (-0.07, 0.05, 0.37)),
         (0.3, 0.3, 0.2, (0.0, 0.0, 0.4)), (-0.3, -0.3, -0.15, (0.0, 0.0, 0.4)),
         (0.25, -0.25, 0.3, (0.0, 0.0, 0.38))]


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    """Rendered target views and the calibration the command wrote from them."""
    d = tmp_path_factory.mktemp("camcal")
    board = parse_board(BOARD).cv_board()
    pic, to_px = charuco_picture(board, 100, 40)
    rays = ray_grid(CAM, SS)
    rng = np.random.default_rng(0)
    names, poses = [], []
    for i, (rx, ry, rz, at) in enumerate(POSES):
        r, t = look_at(rx, ry, rz, CENTRE, at)
        name = str(d / f"view{i}.png")
        cv2.imwrite(name, view(pic, to_px, rays, r, t, SS, rng, noise=1.0, blur_px=BLUR))
        names.append(name)
        poses.append((r, t))
    out = d / "calibration.json"
    assert camera_calibrate_main([*names, "--board", BOARD, "--out", str(out),
                                  "--fps", "500"]) == 0
    return {"dir": d, "names": names, "poses": poses, "rays": rays, "out": out,
            "doc": json.loads(out.read_text()), "board": board, "picture": (pic, to_px)}


def test_recovers_the_camera(rig):
    doc = rig["doc"]
    k = np.array(doc["camera_matrix"])
    print(f"fx {k[0, 0] / CAM.K[0, 0] - 1:+.2e}, fy {k[1, 1] / CAM.K[1, 1] - 1:+.2e} relative; "
          f"c {k[:2, 2] - CAM.K[:2, 2]} px; RMS {doc['reprojection_error_px']['overall_rms']:.3f} px")
    assert abs(k[0, 0] / CAM.K[0, 0] - 1) < 1e-3 and abs(k[1, 1] / CAM.K[1, 1] - 1) < 1e-3
    assert np.allclose(k[:2, 2], CAM.K[:2, 2], atol=1.0)
    err = doc["reprojection_error_px"]
    assert err["overall_rms"] < 0.15 and len(err["per_view"]) == len(POSES)
    assert max(err["per_view"].values()) < 0.2
    assert doc["board"] == BOARD and doc["fps"] == 500 and doc["y_up"] is True
    sheet = cv2.imread(str(rig["dir"] / "calibration_corners.png"))
    assert sheet is not None and sheet.shape[1] == 3 * 400


def test_distortion_is_corrected(rig):
    """Undistorted with the fitted lens, raw pixels land on the true pinhole image."""
    doc = rig["doc"]
    k, dist = np.array(doc["camera_matrix"]), np.array(doc["dist_coeffs"])
    cc, rr = np.meshgrid(np.linspace(40, 600, 15), np.linspace(30, 450, 12))
    raw = np.column_stack([cc.ravel(), rr.ravel()])
    ideal = undistort_px(raw, CAM.K, CAM.dist)  # truth: the raw pixel's pinhole position
    got = undistort_px(raw, k, dist)
    e = np.abs(got - ideal)  # each with its own camera matrix: pixels of a pinhole image
    distortion = np.abs(ideal - raw).max()
    print(f"lens moves points up to {distortion:.2f} px; corrected within {e.max():.4f} px")
    assert distortion > 5  # the lens does move points by pixels
    assert e.max() < 0.15, e.max()


def test_sample_plane_of_the_square_on_view(rig):
    doc = rig["doc"]
    cal = load_calibration(rig["out"])
    # square-on at Z0: the camera's own resolution on the plane is Z0 / f
    mpp_true = Z0 / np.sqrt(CAM.K[0, 0] * CAM.K[1, 1])
    print(f"m_per_px {doc['m_per_px'] / mpp_true - 1:+.2e} relative")
    assert abs(doc["m_per_px"] / mpp_true - 1) < 1e-3
    # true corners of the plane view through the fitted lens + homography -> sample frame
    r, t = rig["poses"][0]
    corners = parse_board(BOARD).corner_points()
    raw = project(CAM, r, t, corners)
    und = undistort_px(raw, np.array(doc["camera_matrix"]), np.array(doc["dist_coeffs"]))
    p = np.column_stack([und, np.ones(len(und))]) @ np.array(doc["homography"]).T
    grid = p[:, :2] / p[:, 2:]
    sample = np.column_stack([corners[:, 0], 0.12 - corners[:, 1]])  # x right, y up
    e = np.abs(grid - cal.sample_to_px(sample)).max()
    print(f"true corners through lens + homography: within {e:.4f} px of the grid")
    assert e < 0.1
    w, h = doc["rectified_size_px"]
    assert 0.8 * 640 < w < 1.5 * 640 and 0.8 * 480 < h < 1.5 * 480


def test_tracking_a_tilted_view_through_the_calibration(rig):
    """A speckled scene on the plane, seen square-on and through the tilted, distorted camera:
    the poses tracked through the calibration equal the square-on ones within 0.05 px."""
    scene = make_scene(nx=3, ny=2)
    mpp, (ox, oy) = scene.cfg.m_per_px, scene.cfg.origin_px
    up = 4  # the scene rendered 4x finer, then seen by the camera
    hi = replace(scene.cfg, width_px=scene.cfg.width_px * up, height_px=scene.cfg.height_px * up,
                 m_per_px=mpp / up, origin_px=(ox * up + 1.5, oy * up + 1.5), supersample=2)
    x0, y0 = parse_board(BOARD).origin_m

    def to_px(xy):  # board (X, Y) -> fine scene pixel
        return np.stack([hi.origin_px[0] + (xy[..., 0] - x0) / hi.m_per_px,
                         hi.origin_px[1] - (y0 - xy[..., 1]) / hi.m_per_px], -1)

    # tilted 20 deg and 11 deg, at the distance where the camera resolves about mpp
    aim = (x0 + 0.034, y0 - 0.0225)
    r, t = look_at(0.35, -0.2, 0.1, aim, (0.01, -0.005, CAM.K[0, 0] * mpp))
    pic, board_px = rig["picture"]
    plane = rig["dir"] / "tilted_plane.png"
    cv2.imwrite(str(plane), view(pic, board_px, rig["rays"], r, t, SS,
                                 np.random.default_rng(5), noise=1.0, blur_px=BLUR))
    out = rig["dir"] / "tilted.json"
    assert camera_calibrate_main([*rig["names"], "--board", BOARD, "--out", str(out),
                                  "--plane", str(plane), "--m-per-px", str(mpp)]) == 0
    cal = load_calibration(out)

    rng = np.random.default_rng(3)
    poses = [np.zeros((scene.n, 3))] + [
        np.column_stack([rng.uniform(-2, 2, (scene.n, 2)) * mpp, rng.uniform(-0.03, 0.03,
                                                                               scene.n)])
        for _ in range(3)]
    flat = [scene.render(p, rng) for p in poses]
    tilted = [view(cv2.GaussianBlur(np.float32(
        replace(scene, cfg=hi).render(p, rng)), (0, 0), 0.5), to_px,
        rig["rays"], r, t, SS, border=float(hi.background_level)) for p in poses]

    def track(calib, frames):
        tr = DICTracker(scene.polygons_m, calib)
        st = init_state(tr, frames[0])
        q = []
        for f in frames[1:]:
            st, fp = track_frame(tr, st, f)
            assert not fp.lost.any()
            q.append(fp.q)
        return np.array(q)

    q_flat, q_tilt = track(scene.calib, flat), track(cal, tilted)
    truth = np.array(poses[1:])
    d_px = np.abs(q_tilt[..., :2] - q_flat[..., :2]) / mpp
    print(f"tilted - square-on: max {d_px.max():.4f} px, rot "
          f"{np.abs(q_tilt[..., 2] - q_flat[..., 2]).max() * 1e3:.3f} mrad; square-on error "
          f"{np.abs(q_flat[..., :2] - truth[..., :2]).max() / mpp:.4f} px")
    assert d_px.max() < 0.05
    assert np.abs(q_tilt[..., 2] - q_flat[..., 2]).max() < 1e-3

    # the same through `metarig track` (frames as PNG files, the calibration file)
    from tracking.cli import track_main

    folder = rig["dir"] / "tilted_frames"
    folder.mkdir()
    for i, f in enumerate(tilted):
        cv2.imwrite(str(folder / f"{i:03d}.png"), f)
    units = rig["dir"] / "units.json"
    units.write_text(json.dumps({"polygons_m": scene.polygons_m.tolist()}))
    npz = rig["dir"] / "tilted.npz"
    assert track_main([str(folder), "--units", str(units), "--calibration", str(out),
                       "--out", str(npz), "-q"]) == 0
    q_cli = np.load(npz)["q"][1:]
    assert np.abs(q_cli[..., :2] - q_flat[..., :2]).max() / mpp < 0.05
    assert np.abs(q_cli[..., 2] - q_flat[..., 2]).max() < 1e-3


def _refused(capsys, argv) -> str:
    assert camera_calibrate_main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("metarig camera-calibrate: error: ") and "\n" not in err
    assert "Traceback" not in err
    return err


def test_refusals(rig, tmp_path, capsys):
    names, out = rig["names"], str(tmp_path / "c.json")
    assert "unknown board kind 'circles'" in _refused(
        capsys, [*names, "--board", "circles:grid=4x11", "--out", out])
    blank = tmp_path / "blank.png"
    cv2.imwrite(str(blank), np.full((480, 640), 128, np.uint8))
    assert "found in 2 of 4 views, at least 3" in _refused(
        capsys, [*names[:2], str(blank), str(blank), "--board", BOARD, "--out", out])
    assert "exceeds --max-error-px 0.01" in _refused(
        capsys, [*names[:4], "--board", BOARD, "--out", out, "--max-error-px", "0.01"])
    assert "no such image file" in _refused(
        capsys, [*names[:3], str(tmp_path / "nope.png"), "--board", BOARD, "--out", out])
    bad = tmp_path / "bad.png"
    bad.write_text("not a picture")
    assert "cannot read image" in _refused(capsys, [*names[:3], str(bad), "--board", BOARD,
                                                    "--out", out])
    assert not (tmp_path / "c.json").exists()


@pytest.mark.parametrize("spec, message", [
    ("charuco:squares=11x8,square=0.015,marker=0.02,dict=DICT_5X5_100", "smaller than"),
    ("charuco:squares=11x8,square=0.015,marker=0.011,dict=DICT_9X9_1", "not an ArUco"),
    ("charuco:squares=11x8,square=0.015,marker=0.011", "missing dict"),
    ("chessboard:inner=9by6,square=0.02", "COLSxROWS"),
    ("chessboard:inner=9x6,square=-1", "positive length"),
    ("chessboard:inner=9x6,square=0.02,colour=red", "unknown field"),
    ("charuco:squares=30x30,square=0.015,marker=0.011,dict=DICT_4X4_50", "markers"),
])
def test_board_spec_errors(spec, message):
    with pytest.raises(CameraCalibrationError, match=message):
        parse_board(spec)


def test_board_spec_round_trip():
    for spec in (BOARD, "chessboard:inner=9x6,square=0.02"):
        assert str(parse_board(spec)) == spec
    b = parse_board("Chessboard: inner = 9x6, square = 0.02")
    assert (b.cols, b.rows, b.square_m, b.origin_m) == (9, 6, 0.02, (0.0, 0.1))


def test_calibration_with_a_lens_alone_undistorts(tmp_path):
    k, dist = CAM.K.tolist(), CAM.dist.tolist()
    path = tmp_path / "c.json"
    path.write_text(json.dumps({"fps": 100, "m_per_px": 1e-4, "origin_px": [0, 0],
                                "y_up": True, "camera_matrix": k, "dist_coeffs": dist}))
    cal = load_calibration(path)
    assert cal.to_json()["dist_coeffs"] == dist
    yy, xx = np.mgrid[0:480, 0:640]
    frame = (128 + 60 * np.sin(xx / 9.0) * np.cos(yy / 7.0)).astype(np.float32)
    got = cal.rectify(frame)
    want = cv2.undistort(frame, CAM.K, CAM.dist)
    assert got.shape == frame.shape
    assert np.abs(got - want)[20:-20, 20:-20].max() < 1.0  # cubic against bilinear
    path.write_text(json.dumps({"fps": 100, "m_per_px": 1e-4, "origin_px": [0, 0],
                                "y_up": True, "camera_matrix": k}))
    with pytest.raises(ValueError, match="come together"):
        load_calibration(path)


def test_chessboard_target(rig, tmp_path):
    """The chessboard route: 9x6 inner corners of 15 mm squares (a 10x7 board), five views;
    the scale comes out about 0.18 % low here (corner RMS 0.015 px: a bias of the corner
    detector the fit turns into focal length), so this checks the route at 0.2 %."""
    ppsq, margin = 100, 60
    cells = (np.add.outer(np.arange(7), np.arange(10)) % 2).astype(np.float32)
    pic = np.full((7 * ppsq + 2 * margin, 10 * ppsq + 2 * margin), 255.0, np.float32)
    pic[margin:-margin, margin:-margin] = 255.0 * np.kron(cells, np.ones((ppsq, ppsq)))

    def to_px(xy):  # board frame: the first inner corner is one square in from the edge
        return (xy + 0.015) * (ppsq / 0.015) + (margin - 0.5)

    names, poses = [], []
    for i, (rx, ry, rz, at) in enumerate(POSES[:5]):
        r, t = look_at(rx, ry, rz, (0.06, 0.0375), at)
        poses.append((r, t))
        names.append(str(tmp_path / f"chess{i}.png"))
        cv2.imwrite(names[-1], view(pic, to_px, rig["rays"], r, t, SS,
                                    np.random.default_rng(i), noise=1.0, blur_px=BLUR))
    out = tmp_path / "chess.json"
    assert camera_calibrate_main([*names, "--board", "chessboard:inner=9x6,square=0.015",
                                  "--out", str(out)]) == 0
    doc = json.loads(out.read_text())
    k = np.array(doc["camera_matrix"])
    print(f"chessboard: fx {k[0, 0] / CAM.K[0, 0] - 1:+.2e}, fy {k[1, 1] / CAM.K[1, 1] - 1:+.2e}"
          f" relative, RMS {doc['reprojection_error_px']['overall_rms']:.3f} px")
    assert abs(k[0, 0] / CAM.K[0, 0] - 1) < 2e-3 and abs(k[1, 1] / CAM.K[1, 1] - 1) < 2e-3
    assert abs(doc["m_per_px"] / (Z0 / np.sqrt(CAM.K[0, 0] * CAM.K[1, 1])) - 1) < 2e-3
    # the sample frame is the board's as printed (the detector's order may come reversed)
    corners = parse_board("chessboard:inner=9x6,square=0.015").corner_points()
    raw = project(CAM, *poses[0], corners)
    und = undistort_px(raw, k, np.array(doc["dist_coeffs"]))
    p = np.column_stack([und, np.ones(len(und))]) @ np.array(doc["homography"]).T
    sample = np.column_stack([corners[:, 0], 0.075 - corners[:, 1]])
    e = np.abs(p[:, :2] / p[:, 2:] - load_calibration(out).sample_to_px(sample)).max()
    assert e < 0.2, e


def test_track_refuses_frames_of_another_size(rig, tmp_path, capsys):
    """`metarig track` with a calibration made for 640 x 480 px and 320 x 240 px frames."""
    from tracking.cli import track_main

    scene = make_scene(nx=2, ny=1)
    units = tmp_path / "units.json"
    units.write_text(json.dumps({"polygons_m": scene.polygons_m.tolist()}))
    frames = tmp_path / "frames"
    frames.mkdir()
    for i in range(2):
        cv2.imwrite(str(frames / f"{i:03d}.png"), cv2.resize(
            cv2.imread(rig["names"][0], cv2.IMREAD_GRAYSCALE), (320, 240)))
    rc = track_main([str(frames), "--units", str(units), "--calibration", str(rig["out"]),
                     "--out", str(tmp_path / "t.npz"), "-q"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "\n" not in err, err
    assert "frame is 320x240 px, the calibration was made for 640x480 px" in err
