"""`metarig track` end to end: image folders, video, MCAP, bad frames, errors, Ctrl-C."""

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from dic_synth import errors_px, make_scene

from ros_nodes import topics as T
from ros_nodes.logic.msgdefs import schema_text
from tracking.batch import run_tracking, save_tracks
from tracking.cli import track_main
from tracking.dic import DICConfig
from tracking.frame_sources import (
    BadFrame,
    SourceError,
    count_frames,
    image_from_msg,
    iter_frames,
    open_source,
)

N_T = 12


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """Rendered frames of a 4x2 lattice drifting and turning, with inputs and ground truth."""
    root = tmp_path_factory.mktemp("rec")
    scene = make_scene(4, 2)
    rng = np.random.default_rng(0)
    k = np.arange(N_T)[:, None]
    truth = np.zeros((N_T, scene.n, 3))
    truth[..., 0] = 0.35 * k * scene.cfg.m_per_px
    truth[..., 1] = -0.2 * k * scene.cfg.m_per_px
    truth[..., 2] = 0.004 * k
    frames = [scene.render(p, rng) for p in truth]
    folder = root / "frames"
    folder.mkdir()
    for i, f in enumerate(frames):
        cv2.imwrite(str(folder / f"frame_{i:05d}.png"), f)
    (root / "units.json").write_text(json.dumps({"polygons_m": scene.polygons_m.tolist()}))
    (root / "cal.json").write_text(json.dumps(scene.calib.to_json()))
    return {"root": root, "scene": scene, "truth": truth, "frames": frames, "folder": folder}


def _args(rec, source, out, *extra):
    return [str(source), "--units", str(rec["root"] / "units.json"), "--calibration",
            str(rec["root"] / "cal.json"), "--out", str(out), "-q", *extra]


@pytest.mark.parametrize("workers", [1, 2])
def test_track_folder_matches_truth_for_any_worker_count(recording, tmp_path, workers):
    out = tmp_path / "tracks.npz"
    assert track_main(_args(recording, recording["folder"], out,
                                      "--workers", str(workers), "--block", "5")) == 0
    d = np.load(out)
    assert set(d.files) >= {"t", "q", "qdot", "quality", "lost"}
    assert d["q"].shape == (N_T, 8, 3) and d["q"].dtype == np.float64
    np.testing.assert_allclose(d["t"], np.arange(N_T) / recording["scene"].calib.fps)
    assert not d["lost"].any() and bool(d["complete"])
    pos, rot = errors_px(recording["scene"], d["q"], recording["truth"])
    assert pos < 0.01 and rot < 0.5
    assert np.isnan(d["qdot"][0]).all()
    # rates amplify the per-frame error by fps: 0.1 mrad -> 0.1 rad/s at 1000 fps
    np.testing.assert_allclose(d["qdot"][1:, :, 2], 0.004 * 1000.0, atol=0.6)


def test_bad_frames_in_folder_are_flagged(recording, tmp_path):
    folder = tmp_path / "frames"
    folder.mkdir()
    for i, f in enumerate(recording["frames"]):
        cv2.imwrite(str(folder / f"f{i:03d}.png"), f)
    (folder / "f004.png").write_bytes(b"not a png at all")
    cv2.imwrite(str(folder / "f007.png"), np.zeros_like(recording["frames"][7]))
    out = tmp_path / "t.npz"
    assert track_main(_args(recording, folder, out, "--workers", "1")) == 0
    d = np.load(out)
    assert d["lost"][[4, 7]].all() and np.isnan(d["q"][[4, 7]]).all()
    good = np.setdiff1d(np.arange(N_T), [4, 7])
    assert not d["lost"][good].any()
    pos, _ = errors_px(recording["scene"], d["q"][good], recording["truth"][good])
    assert pos < 0.01


def _write_mcap(path, frames, bad_index=None):
    from mcap_ros2.writer import Writer

    with open(path, "wb") as f:
        w = Writer(f)
        schema = w.register_msgdef("sensor_msgs/msg/Image", schema_text("sensor_msgs/msg/Image"))
        for k, img in enumerate(frames):
            data = img.tobytes() if k != bad_index else img.tobytes()[:100]
            msg = {"header": {"stamp": {"sec": 0, "nanosec": k * 1000}, "frame_id": "cam"},
                   "height": img.shape[0], "width": img.shape[1], "encoding": "mono8",
                   "is_bigendian": 0, "step": img.shape[1], "data": data}
            w.write_message(T.IMAGE.name, schema, msg, log_time=k * 1_000_000,
                            publish_time=k * 1_000_000)
        w.finish()


def test_track_mcap_recording(recording, tmp_path):
    path = tmp_path / "rec.mcap"
    _write_mcap(path, recording["frames"], bad_index=5)
    spec = open_source(path)
    assert spec.kind == "mcap" and spec.topic == T.IMAGE.name
    assert count_frames(spec) == N_T
    items = list(iter_frames(spec))
    assert isinstance(items[5][1], BadFrame)
    np.testing.assert_array_equal(items[3][1], recording["frames"][3])
    out = tmp_path / "t.npz"
    assert track_main(_args(recording, path, out, "--workers", "2")) == 0
    d = np.load(out)
    assert d["lost"][5].all() and not d["lost"][np.arange(N_T) != 5].any()
    pos, rot = errors_px(recording["scene"], d["q"], recording["truth"])
    assert pos < 0.01 and rot < 0.5


def test_track_video_file(recording, tmp_path):
    path = tmp_path / "clip.avi"
    h, w = recording["frames"][0].shape
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"FFV1"), 30.0, (w, h), False)
    if not writer.isOpened():
        writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (w, h), False)
    for f in recording["frames"]:
        writer.write(f)
    writer.release()
    out = tmp_path / "t.npz"
    assert track_main(_args(recording, path, out, "--workers", "1")) == 0
    d = np.load(out)
    assert d["q"].shape[0] == N_T and not d["lost"].any()
    pos, _ = errors_px(recording["scene"], d["q"], recording["truth"])
    assert pos < 0.05  # a lossy codec may have been the only one available


def test_image_from_msg_encodings():
    class Msg:
        def __init__(self, **kw):
            self.__dict__.update(kw)

    img16 = np.arange(12, dtype=np.uint16).reshape(3, 4) * 1000
    m = Msg(encoding="mono16", is_bigendian=1, height=3, width=4, step=8,
            data=img16.astype(">u2").tobytes())
    np.testing.assert_array_equal(image_from_msg(m), img16)
    rgb = np.zeros((2, 2, 3), np.uint8)
    rgb[..., 0] = 200
    m = Msg(encoding="rgb8", is_bigendian=0, height=2, width=2, step=6, data=rgb.tobytes())
    assert image_from_msg(m)[0, 0, 2] == 200  # returned as BGR
    with pytest.raises(ValueError, match="encoding"):
        image_from_msg(Msg(encoding="yuv422", is_bigendian=0, height=1, width=1, step=2,
                           data=b"00"))


def _put(rec, args, slot, name, text):
    path = rec["root"] / name
    path.write_text(text)
    args[slot] = str(path)


@pytest.mark.parametrize(
    ("slot", "name", "text", "message"),
    [
        (0, None, None, "no such file"),
        (4, "badcal.json", '{"fps": 1}', "badcal.json"),
        (4, "badcal2.json", "[1, 2", "not valid JSON"),
        (2, "nounits.json", "{}", "polygons_m"),
        (0, "notes.txt", "x", "not a folder"),
    ],
)
def test_user_errors_are_reported_without_traceback(recording, tmp_path, capsys, slot, name,
                                                     text, message):
    args = _args(recording, recording["folder"], tmp_path / "t.npz")
    if name is None:
        args[slot] = str(recording["root"] / "nowhere")
    else:
        _put(recording, args, slot, name, text)
    assert track_main(args) == 2
    err = capsys.readouterr().err
    assert "metarig track: error:" in err and message in err and "Traceback" not in err


@pytest.mark.parametrize(("flag", "value", "message"), [
    ("--workers", "0", "must be at least 1"),  # 0 and -3 were one worker, silently
    ("--workers", "-3", "must be at least 1"),
    ("--block", "0", "must be at least 1"),
    ("--threads", "-1", "must be 0 or more"),
    ("--max-frames", "-1", "must be 0 or more"),
    ("--min-points", "-5", "must be 0 or more"),
    ("--search-radius-px", "-2", "must be 0 or more"),
    ("--prefilter-sigma-px", "-1", "must be 0 or more"),
    ("--out", "", "--out is empty"),
])
def test_a_bad_count_or_empty_flag_is_refused_in_one_line(tmp_path, capsys, flag, value,
                                                          message):
    args = [str(tmp_path), "--units", "u.json", "--calibration", "c.json", "--out",
            str(tmp_path / "t.npz"), "-q", flag, value]
    with pytest.raises(SystemExit) as e:
        track_main(args)
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if "error" in line]
    assert e.value.code == 2 and "Traceback" not in err
    assert lines == [f"metarig track: error: argument {flag}: {message}, got {value}"
                     if value else f"metarig track: error: argument {flag}: {message}"]


def _gap_squares(scene):
    """Small squares (16 px) centred where four units meet: background only, no speckle."""
    mpp = scene.cfg.m_per_px
    from hardware_sim.camera import square_lattice_polygons

    return square_lattice_polygons(3, 1, 60 * mpp, 16 * mpp, (60 * mpp, 60 * mpp))


@pytest.mark.parametrize(
    ("outlines", "message"),
    [
        (lambda sc: make_scene(6, 3).polygons_m, "do not fit the frames: 10 of 18 units"),
        (_gap_squares, "do not match the frames: 3 of 3 units show no speckle texture"),
    ],
    ids=["bigger-lattice", "outlines-off-the-units"],
)
def test_outlines_of_another_lattice_are_refused(recording, tmp_path, capsys, outlines,
                                                  message):
    """Outlines of another design: one error line, exit 2, no traceback, no output file."""
    units = tmp_path / "other.json"
    units.write_text(json.dumps({"polygons_m": outlines(recording["scene"]).tolist()}))
    out = tmp_path / "t.npz"
    args = _args(recording, recording["folder"], out, "--workers", "2")
    args[2] = str(units)
    assert track_main(args) == 2
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("metarig track: error:"), lines
    assert message in lines[0] and "another design" in lines[0]
    assert not out.exists()


def test_open_source_errors(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(SourceError, match="no \\*.png"):
        open_source(tmp_path / "empty")
    (tmp_path / "x.mcap").write_bytes(b"garbage")
    with pytest.raises(SourceError, match="not a readable MCAP"):
        open_source(tmp_path / "x.mcap")


class _InterruptingBar:
    """Stands in for tqdm: raises KeyboardInterrupt (Ctrl-C) on its second update."""

    def __init__(self, *a, **k):
        self.calls = 0

    def update(self, n):
        self.calls += 1
        if self.calls == 2:
            raise KeyboardInterrupt

    def close(self):
        pass


@pytest.mark.parametrize("workers", [1, 2])
def test_ctrl_c_keeps_finished_frames(recording, tmp_path, monkeypatch, workers):
    import tqdm

    monkeypatch.setattr(tqdm, "tqdm", _InterruptingBar)
    spec = open_source(recording["folder"])
    sc = recording["scene"]
    res = run_tracking(spec, sc.polygons_m, sc.calib, DICConfig(), workers=workers,
                                 block=2)
    assert not res.complete
    n = res.q.shape[0]
    assert 2 <= n < N_T and n % 2 == 0
    pos, _ = errors_px(sc, res.q, recording["truth"][:n])
    assert pos < 0.01
    out = save_tracks(tmp_path / "partial.npz", res, sc.calib.fps)
    assert not bool(np.load(out)["complete"])


RECORDING = Path(__file__).resolve().parents[1] / "recordings" / "focusing-12x8"


@pytest.mark.skipif(not (RECORDING / "recording.mcap").exists(), reason="no sample recording")
def test_track_sample_recording_against_its_ground_truth(tmp_path):
    """The simulated rig's recording (96 units of ~10 px, motion blur, noise) vs its truth."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    out = tmp_path / "t.npz"
    args = [str(RECORDING / "recording.mcap"), "--units", str(RECORDING / "design.json"),
            "--calibration", str(RECORDING / "calibration.json"), "--out", str(out), "-q",
            "--margin-px", "1.5", "--min-points", "16"]
    assert track_main(args) == 0
    d = np.load(out)
    polys = np.array(json.loads((RECORDING / "design.json").read_text())["polygons_m"])
    from metarig.polygon import area_centroids

    c0 = area_centroids(polys)
    truth = []
    with open(RECORDING / "recording.mcap", "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for *_, m in reader.iter_decoded_messages(topics=["/camera/ground_truth"],
                                                  log_time_order=True):
            truth.append(np.stack([np.array(m.x) - c0[:, 0], np.array(m.y) - c0[:, 1],
                                   np.array(m.theta)], axis=1))
    truth = np.array(truth)
    assert d["q"].shape == truth.shape and not d["lost"].any()
    # the truth is the pose at the end of a half-frame exposure: compare mid-exposure poses,
    # relative to the first frame (which the tracker takes as its reference)
    mid = truth.copy()
    mid[1:] = truth[1:] - 0.25 * (truth[1:] - truth[:-1])
    e = (d["q"] - (mid - truth[0]))[1:]
    pos = np.sqrt(np.mean((e[..., :2] ** 2).sum(-1))) / 1.2e-3
    assert pos < 0.1
    assert np.sqrt(np.mean(e[..., 2] ** 2)) < 0.03


def test_separate_reference_image(recording, tmp_path):
    """--reference: poses are measured from that image; the source may start displaced."""
    folder = tmp_path / "frames"
    folder.mkdir()
    for i, f in enumerate(recording["frames"][3:]):
        cv2.imwrite(str(folder / f"f{i:03d}.png"), f)
    ref = tmp_path / "ref.png"
    cv2.imwrite(str(ref), recording["frames"][0])
    out = tmp_path / "t.npz"
    assert track_main(_args(recording, folder, out, "--reference", str(ref))) == 0
    d = np.load(out)
    assert d["q"].shape[0] == N_T - 3 and not d["lost"].any()
    pos, rot = errors_px(recording["scene"], d["q"], recording["truth"][3:])
    assert pos < 0.01 and rot < 0.5
