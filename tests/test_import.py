"""`metarig import`: a lab's camera files and drive signal become a run folder that `metarig
compare` and `metarig calibrate` read as they read the rig's.

The experiment is the sample recording `recordings/focusing-12x8` (160x120 px, 51 frames at
1000 fps) taken apart and written in each format by its own library (PNG folder + CSV, MRAW +
CIH/CIHX + TDMS, TIFF stack, the committed CINE sample); every import is read back by an
independent reader (the MCAP library's ROS 2 decoder) and set against the PNG route, and the
comparison of the PNG and MRAW + TDMS imports against the original run's.
"""

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

import import_formats as F

from metarig.cli import main

ROOT = Path(__file__).resolve().parents[1]
RUN = ROOT / "recordings" / "focusing-12x8"
CINE = ROOT / "tests" / "data" / "tiny.cine"
SAMPLE = ["--scene", "focusing-24x16", "--nx", "12", "--ny", "8"]


@pytest.fixture(scope="module")
def exp() -> F.Experiment:
    return F.export_run(RUN)


@pytest.fixture(scope="module")
def files(exp, tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("files")
    return {"png": F.write_png(exp.frames, d / "png"),
            "csv": F.write_csv(exp.signal_t_s, exp.signal_u_m, d / "drive.csv"),
            "tdms": F.write_tdms(exp.signal_t_s, exp.signal_u_m, d / "drive.tdms"),
            "cih": F.write_mraw(exp.frames, d / "mraw8" / "take.mraw", exp.fps,
                                exp.start_frame)}


def _import(args: list[str], out: Path, capsys) -> tuple[int, str]:
    capsys.readouterr()
    code = main(["import", *map(str, args), "--calibration", str(RUN / "calibration.json"),
                 "--out", str(out), "-q"])
    return code, capsys.readouterr().err


@pytest.fixture(scope="module")
def png_run(exp, files, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("runs") / "png"
    assert main(["import", str(files["png"]), "--fps", f"{exp.fps:g}", "--trigger-offset",
                 repr(float(exp.frame_t_s[0])), "--signal", str(files["csv"]), *SAMPLE,
                 "--calibration", str(RUN / "calibration.json"), "--out", str(out), "-q"]) == 0
    return out


def _content(run: Path) -> dict:
    """What a run's MCAP holds, decoded by the MCAP library's ROS 2 decoder (not ours)."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    got = {"frames": [], "frame_ns": [], "info_ns": [], "shaker": [], "k0": None}
    with open(run / "recording.mcap", "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _s, ch, rec, msg in reader.iter_decoded_messages(log_time_order=True):
            if ch.topic == "/camera/image_raw":
                dt = np.uint8 if msg.encoding == "mono8" else np.dtype("<u2")
                got["frames"].append(np.frombuffer(msg.data, dt).reshape(msg.height, msg.width))
                got["frame_ns"].append(rec.log_time)
            elif ch.topic == "/camera/camera_info":
                got["info_ns"].append(rec.log_time)
                got["k0"] = msg.k[0]
            elif ch.topic == "/shaker/joint_states":
                assert list(msg.name) == ["shaker"]
                got["shaker"].append((msg.header.stamp.sec * 1e9 + msg.header.stamp.nanosec,
                                      msg.position[0]))
            elif ch.topic == "/rig/design":
                got["design"] = json.loads(msg.data)
    got["frames"] = np.stack(got["frames"])
    got["shaker"] = np.array(got["shaker"])
    return got


def test_png_route_holds_the_experiment(exp, png_run):
    c = _content(png_run)
    assert np.array_equal(c["frames"], exp.frames)
    assert c["frame_ns"] == c["info_ns"]
    assert np.allclose(np.array(c["frame_ns"]) * 1e-9, exp.frame_t_s, atol=1e-9, rtol=0)
    assert c["k0"] == pytest.approx(1 / 1.2e-3)
    # the signal on the rig clock: from 0 to one frame after the last frame, mm -> m
    keep = exp.signal_t_s <= exp.frame_t_s[-1] + 1 / exp.fps + 1e-12
    assert np.allclose(c["shaker"][:, 0] * 1e-9, exp.signal_t_s[keep], atol=1e-9, rtol=0)
    assert np.allclose(c["shaker"][:, 1], exp.signal_u_m[keep], rtol=1e-12, atol=1e-15)
    ref = json.loads((RUN / "design.json").read_text())["polygons_m"]
    assert np.allclose(c["design"]["polygons_m"], ref, atol=1e-9)
    assert c["design"]["specimen_imperfections"]["level"] == 0  # a real sample, not simulated
    run = json.loads((png_run / "run.json").read_text())
    assert run["import"]["timing"]["fps_from"] == "flag"
    assert json.loads((png_run / "calibration.json").read_text())["fps"] == exp.fps
    assert not list(png_run.parent.glob(".*.part"))


def _same_recording(a: dict, b: dict, signal_too: bool = True) -> None:
    assert np.array_equal(a["frames"], b["frames"])
    assert a["frame_ns"] == b["frame_ns"]
    if signal_too:
        assert a["shaker"].shape == b["shaker"].shape
        assert np.allclose(a["shaker"], b["shaker"], rtol=1e-12, atol=1)


def test_mraw_tdms_route_compares_as_png_route_and_as_the_rig_run(exp, files, png_run,
                                                                  tmp_path, capsys):
    """The issue's acceptance: MRAW + TDMS imported, tracked and compared with the PNG route's
    figures, which are the original run's."""
    from ros_nodes.recorded_compare import compare_recording
    from ros_nodes.recorded_run import pulse_inputs

    out = tmp_path / "mraw"
    # frame rate and trigger offset from the CIH, the signal's unit from the TDMS channel
    code, err = _import([files["cih"], "--signal", files["tdms"], "--channel",
                         f"{F.GROUP}/{F.CHANNEL}", *SAMPLE], out, capsys)
    assert code == 0, err
    run = json.loads((out / "run.json").read_text())
    assert run["import"]["timing"]["fps_from"] == run["import"]["timing"]["offset_from"] == "file"
    _same_recording(_content(out), _content(png_run))
    s_png = compare_recording(png_run, tmp_path / "cmp_png", poses="track", workers=1)
    s_mraw = compare_recording(out, tmp_path / "cmp_mraw", poses="track", workers=1)
    s_rig = compare_recording(RUN, tmp_path / "cmp_rig", poses="track", workers=1)
    keys = ("velocity_nrmse", "energy_map_correlation", "target_peak_ke_rel_err",
            "max_displacement_error_m", "lost_units", "frames")
    print("NRMSE rig %.6f png %.6f mraw+tdms %.6f" % tuple(
        s["velocity_nrmse"] for s in (s_rig, s_png, s_mraw)))
    for k in keys:
        assert s_mraw[k] == s_png[k], k
        assert s_png[k] == pytest.approx(s_rig[k], rel=1e-6, abs=1e-12), k
    # what `metarig calibrate` fits to (pulse): the same poses and input as the rig run's
    a, b = pulse_inputs(out, "track", workers=1), pulse_inputs(RUN, "track", workers=1)
    assert np.array_equal(a[1].q, b[1].q, equal_nan=True)
    assert a[2] == b[2]
    assert np.allclose(a[3][0], b[3][0]) and np.allclose(a[3][1], b[3][1])


@pytest.mark.parametrize("form", ["cihx16", "tiff"])
def test_other_formats_equal_png_route(exp, files, png_run, tmp_path, capsys, form):
    if form == "cihx16":  # 12 significant bits in 16, header as XML
        import pyMRAW

        raw = exp.frames.astype(np.uint16) * 16
        cih = F.write_mraw(raw, tmp_path / "take.mraw", exp.fps, exp.start_frame, bits=16)
        cih.unlink()
        n, h, w = raw.shape
        src = F.write_cihx(tmp_path / "take.cihx", n, w, h, 16, exp.fps, exp.start_frame)
        assert pyMRAW.get_cih(str(src))["Total Frame"] == len(raw)
        expected = raw
        extra = []
    else:
        src = F.write_tiff(exp.frames, tmp_path / "stack.tif", exp.fps)
        expected = exp.frames
        extra = ["--trigger-offset", repr(float(exp.frame_t_s[0]))]  # a TIFF records no trigger
    code, err = _import([src, "--signal", files["csv"], *extra, *SAMPLE], tmp_path / "run",
                        capsys)
    assert code == 0, err
    got, ref = _content(tmp_path / "run"), _content(png_run)
    assert np.array_equal(got["frames"], expected)
    assert got["frame_ns"] == ref["frame_ns"]
    assert np.array_equal(got["shaker"], ref["shaker"])


def test_cine_sample_equals_png_route(tmp_path, capsys):
    """The committed CINE (`tests/data/make_tiny_cine.py`) against the same crop as 16-bit
    PNGs; pycine, where installed, reads the same pixels."""
    import cv2

    import importlib.util

    spec = importlib.util.spec_from_file_location("make_tiny_cine", CINE.with_name(
        "make_tiny_cine.py"))
    maker = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(maker)
    FIRST_IMAGE_NO, FPS, cine_bytes, frames = (maker.FIRST_IMAGE_NO, maker.FPS,
                                               maker.cine_bytes, maker.frames)
    crop = frames()
    assert CINE.read_bytes() == cine_bytes(crop, FPS, FIRST_IMAGE_NO)  # the script made it
    png = tmp_path / "png"
    png.mkdir()
    for k, f in enumerate(crop):
        cv2.imwrite(str(png / f"{k:03d}.png"), f)
    calib = tmp_path / "calibration.json"
    calib.write_text(json.dumps({"fps": 1.0, "m_per_px": 1.2e-3, "origin_px": [0, 0],
                                 "y_up": True}))
    runs = {}
    for name, args in {"cine": [CINE], "png": [png, "--fps", FPS, "--trigger-offset",
                                               FIRST_IMAGE_NO / FPS]}.items():
        capsys.readouterr()
        assert main(["import", *map(str, args), *SAMPLE, "--calibration", str(calib),
                     "--out", str(tmp_path / f"run_{name}"), "-q"]) == 0, \
            capsys.readouterr().err
        runs[name] = _content(tmp_path / f"run_{name}")
    _same_recording(runs["cine"], runs["png"], signal_too=False)
    assert np.array_equal(runs["cine"]["frames"], crop)
    assert runs["cine"]["frame_ns"][0] == FIRST_IMAGE_NO * 1_000_000
    try:
        from pycine.raw import read_frames
    except ImportError:
        return
    images, setup, _bpp = read_frames(str(CINE))
    assert setup.FrameRate == FPS
    assert np.array_equal(np.stack(list(images)), crop)


def test_track_reads_camera_files(files, exp):
    from tracking.frame_sources import count_frames, iter_frames, open_source

    spec = open_source(files["cih"])
    assert spec.kind == "mraw" and count_frames(spec) == len(exp.frames)
    assert np.array_equal(np.stack([f for _k, f in iter_frames(spec)]), exp.frames)


# bad inputs: one line, exit code 2, nothing written --------------------------------------------
def _refused(args, tmp_path, capsys, words: tuple[str, ...]) -> str:
    out = tmp_path / "out"
    code, err = _import(args, out, capsys)
    assert code == 2
    line = err.strip()
    assert "\n" not in line and "Traceback" not in line, err
    assert line.startswith("metarig import: error: ")
    for w in words:
        assert w in line, line
    assert not out.exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".out.")]
    return line


def test_truncated_mraw(files, exp, tmp_path, capsys):
    d = tmp_path / "cut"
    shutil.copytree(files["cih"].parent, d)
    mraw = d / "take.mraw"
    mraw.write_bytes(mraw.read_bytes()[: int(mraw.stat().st_size * 0.6)])
    _refused([d / "take.cih", *SAMPLE], tmp_path, capsys, ("cut short", "30 whole frames",
                                                            "51"))


def test_cihx_that_does_not_match_its_mraw(files, exp, tmp_path, capsys):
    d = tmp_path / "other"
    d.mkdir()
    shutil.copy(files["cih"].with_suffix(".mraw"), d / "take.mraw")
    n, h, w = exp.frames.shape
    F.write_cihx(d / "take.cihx", n, w - 10, h, 8, exp.fps, 0)  # another camera's ROI
    _refused([d / "take.mraw", *SAMPLE], tmp_path, capsys, ("do not match", "take.cihx"))


def test_tdms_without_the_channel(files, tmp_path, capsys):
    _refused([files["cih"], "--signal", files["tdms"], "--channel", "Drive/Accelerometer",
              *SAMPLE], tmp_path, capsys, ("no channel 'Drive/Accelerometer'", "Drive/Shaker"))


def test_frame_rate_missing_from_file_and_flags(files, tmp_path, capsys):
    _refused([files["png"], "--trigger-offset", "0", *SAMPLE], tmp_path, capsys,
             ("no frame rate", "--fps"))


def test_calibration_with_too_large_reprojection_error(files, tmp_path, capsys):
    doc = json.loads((RUN / "calibration.json").read_text())
    doc["reprojection_error_px"] = {"overall_rms": 2.5}
    bad = tmp_path / "blurred.json"
    bad.write_text(json.dumps(doc))
    code, err = 0, ""
    capsys.readouterr()
    out = tmp_path / "out"
    code = main(["import", str(files["cih"]), *SAMPLE, "--calibration", str(bad), "--out",
                 str(out), "-q"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and "\n" not in err and "2.5 px" in err and "blurred.json" in err
    assert not out.exists()


def test_frames_of_another_size_than_the_calibration(files, tmp_path, capsys):
    doc = json.loads((RUN / "calibration.json").read_text())
    doc["image_size_px"] = [640, 480]
    cal = tmp_path / "cal.json"
    cal.write_text(json.dumps(doc))
    capsys.readouterr()
    out = tmp_path / "out"
    code = main(["import", str(files["cih"]), *SAMPLE, "--calibration", str(cal), "--out",
                 str(out), "-q"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and "\n" not in err and "160x120" in err and "640x480" in err, err
    assert not out.exists()


def test_interrupted_import_leaves_nothing(files, tmp_path, monkeypatch):
    """Ctrl-C half-way through the frames: no run folder, no staging folder."""
    from ros_nodes.logic import run_import as R

    real = R._write_sample

    def stop_late(rec, ns, u):
        if ns > 40_000_000:
            raise KeyboardInterrupt
        real(rec, ns, u)

    monkeypatch.setattr(R, "_write_sample", stop_late)
    out = tmp_path / "out"
    with pytest.raises(KeyboardInterrupt):
        R.import_run(R.ImportRequest(frames=str(files["cih"]), out=str(out),
                                     signal=str(files["csv"]), scene="focusing-24x16", nx=12,
                                     ny=8, calibration=str(RUN / "calibration.json")))
    assert list(tmp_path.iterdir()) == []


def test_existing_output_is_refused(files, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    code, err = _import([files["cih"], *SAMPLE], out, capsys)
    assert code == 2 and "not empty" in err and (out / "keep.txt").read_text() == "mine"


def test_hand_built_messages_match_rclpy():
    """The import's joint states, camera info and strings decode as rclpy's own."""
    from rclpy.serialization import deserialize_message, serialize_message
    from sensor_msgs.msg import CameraInfo, JointState
    from std_msgs.msg import String

    from ros_nodes import convert
    from ros_nodes.logic import cdr

    ns = 12_345_678_901
    for ours, theirs in [
        (cdr.joint_state_cdr(ns, ["shaker"], [1e-3]), convert.shaker_state(ns, 1e-3, 0.0)),
        (cdr.camera_info_cdr(ns, 160, 120, 1.2e-3), convert.camera_info(ns, 160, 120, 1.2e-3)),
        (cdr.string_cdr('{"a": 1}'), convert.text('{"a": 1}')),
    ]:
        t = type(theirs)
        if t is JointState:
            theirs.velocity = []
        assert t in (JointState, CameraInfo, String)
        assert len(ours) == len(serialize_message(theirs))
        assert deserialize_message(ours, t) == theirs
