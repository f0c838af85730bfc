"""`metarig compare` on the sample recordings: run folder files read back by independent readers,
and one clear line for every recording that cannot be compared."""

import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from ros_nodes import topics as T
from ros_nodes.cli_compare import compare_main

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "recordings" / "precompression-12x8"
SMALL_UNITS = ["--margin-px", "1.5", "--min-points", "16"]  # 12 px units in the samples


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def compared(tmp_path_factory):
    out = tmp_path_factory.mktemp("cmp")
    before = _digest(SAMPLE / "recording.mcap")
    assert compare_main([str(SAMPLE), "--out", str(out), "--poses", "track", "-q",
                         *SMALL_UNITS]) == 0
    assert _digest(SAMPLE / "recording.mcap") == before  # the source is never touched
    return out


def test_run_folder_holds_summary_plots_trajectories(compared):
    s = json.loads((compared / "summary.json").read_text())
    for key in ("velocity_nrmse", "energy_map_correlation", "target_peak_ke_rel_err",
                "max_displacement_error_m", "lost_units", "onset_s", "mcap", "rrd"):
        assert key in s
    # units 24 and 56 (10 px wide) are the hard ones: without the tracker's prefilter they came
    # out 50-98 mrad off the truth at ZNCC 0.97 and were flagged lost from frame 19 on; with it
    # (0.8 px) they stay within 28 mrad of the truth at a stated 12-16 mrad and no unit is
    # lost. Up to two may still sit near the 10 mrad / 0.5 px bounds of the drift check on
    # another CPU, so the bound is not exact
    assert s["lost_units"] <= 2 and s["input_source"] == "tracked"
    assert s["precompression_m"] == pytest.approx(0.02 * 0.105, rel=0.02)  # 2 % of (8-1) s
    # 12 px units at 1.2 mm/px: the tracking noise dominates (measured: velocity NRMSE 0.094
    # tracked, 0.068 of it expected from the stated pose errors, 0.029 on the recording's
    # ground-truth poses; energy-map correlation 0.9997; target peak KE -0.025; max
    # displacement error 0.42 mm = 0.35 px). Bounds at ~2x: the recording is fixed and tracking
    # and simulation are deterministic, so another CPU moves these by rounding in the DIC
    # solves and the engine only, orders below the margins.
    assert s["velocity_nrmse"] < 0.2 and s["energy_map_correlation"] > 0.998
    assert 0.03 < s["velocity_noise_nrmse"] < s["velocity_nrmse"]
    assert abs(s["target_peak_ke_rel_err"]) < 0.08 and s["max_displacement_error_m"] < 2e-3
    for png in ("velocity_maps.png", "target_ke.png", "row_peak_ke.png", "tracking_quality.png"):
        assert (compared / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    from metarig.trajectory import Trajectory

    tracks = Trajectory.load_npz(compared / "tracks.npz")
    assert tracks.n_t == 51 and tracks.lost is not None and tracks.n_units == 96


def test_the_mcap_gains_the_comparison_topics(compared):
    from rosbags.highlevel import AnyReader

    with AnyReader([compared / "recording.mcap"]) as reader:
        counts = {}
        result = None
        for con, _, raw in reader.messages():
            counts[con.topic] = counts.get(con.topic, 0) + 1
            if con.topic == T.COMPARE_RESULT.name:
                result = reader.deserialize(raw, con.msgtype)
    assert counts[T.IMAGE.name] == 51 and counts[T.IMAGE_PREVIEW.name] == 51
    assert counts[T.POSES.name] == 51 and counts[T.COMPARE_SIMULATED.name] == 51
    assert counts[T.COMPARE_RESULT.name] == 1 and counts[T.COMPARE_SUMMARY.name] == 1
    summary = json.loads((compared / "summary.json").read_text())
    assert result.velocity_nrmse == pytest.approx(summary["velocity_nrmse"])
    assert len(result.target_ke_exp) == len(result.t) > 10


def test_the_rerun_recording_reads_back(compared):
    from rerun.chunk import RrdReader

    paths = set()
    for chunk in RrdReader(str(compared / "comparison.rrd")).store().stream():
        paths.add(str(chunk.entity_path))
    assert {"/experiment/units", "/simulation/units", "/camera/image"} <= paths


def test_a_rerun_of_compare_replaces_its_results_in_place(compared, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(compared, run)
    for f in ("summary.json", "comparison.rrd"):
        (run / f).unlink()
    shutil.copy(SAMPLE / "calibration.json", run)
    assert compare_main([str(run), "-q", *SMALL_UNITS]) == 0  # run folder: MCAP in place
    from mcap.reader import make_reader

    with open(run / "recording.mcap", "rb") as f:
        stats = make_reader(f).get_summary()
    by_topic = {c.topic: stats.statistics.channel_message_counts.get(cid, 0)
                for cid, c in stats.channels.items()}
    assert by_topic[T.COMPARE_RESULT.name] == 1 and by_topic[T.POSES.name] == 51


@pytest.mark.parametrize(("flag", "value", "message"), [
    ("--margin-px", "-1", "must be 0 or more, got -1"),  # was DICConfig's traceback
    ("--calibration", "", "--calibration is empty"),  # was the run folder's, silently
    ("--workers", "0", "must be at least 1, got 0"),
])
def test_bad_tracking_flags_are_refused_in_one_line(tmp_path, capsys, flag, value, message):
    with pytest.raises(SystemExit) as e:
        compare_main([str(SAMPLE), "--out", str(tmp_path / "o"), "-q", flag, value])
    lines = [line for line in capsys.readouterr().err.splitlines() if "error" in line]
    assert e.value.code == 2 and lines == [f"metarig compare: error: argument {flag}: {message}"]
    assert not (tmp_path / "o").exists()


def _rewritten(src: Path, dst_dir: Path, topic: str, messages) -> Path:
    """A copy of the recording whose `topic` holds `messages` instead."""
    from ros_nodes.logic.mcap_append import append_messages

    dst_dir.mkdir(parents=True, exist_ok=True)
    shutil.copy(src.parent / "calibration.json", dst_dir)
    return append_messages(src, dst_dir / "recording.mcap", {topic: T.BY_NAME[topic].type},
                           messages, replace=(topic,))


def _truth_messages(n: int | None = None, lose_all: bool = False):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    from ros_nodes import convert
    from ros_nodes.logic.mcap_append import NewMessage

    out = []
    with open(SAMPLE / "recording.mcap", "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _s, _c, rec, m in reader.iter_decoded_messages(topics=[T.GROUND_TRUTH.name]):
            q = np.zeros((len(m.ids), 3))
            ref = np.stack([m.x, m.y], axis=-1)
            lost = np.ones(len(m.ids), bool) if lose_all else None
            ns = int(m.header.stamp.sec) * 10**9 + int(m.header.stamp.nanosec)
            out.append(NewMessage(T.POSES.name, rec.log_time, convert.serialize(
                convert.unit_poses(ns, q, ref, lost=lost))))
    return out[:n] if n else out


@pytest.mark.parametrize("case, message", [
    ("missing", "no such file or folder"),
    ("not-mcap", "not an .mcap recording"),
    ("two-frames", "needs 3 or more"),
    ("all-lost", "every unit was lost"),
    ("other-design", "does not match the recording"),
    ("no-poses-no-frames", "neither poses nor camera frames"),
    ("cut-mcap", "not a readable MCAP recording"),  # cut to half its bytes
    ("cut-calibration", "calibration.json: damaged or unreadable camera calibration"),
])
def test_recordings_that_cannot_be_compared_give_one_line(case, message, tmp_path, capsys):
    src = SAMPLE / "recording.mcap"
    if case == "missing":
        path = tmp_path / "nope.mcap"
    elif case == "not-mcap":
        path = tmp_path / "x.json"
        path.write_text("{}")
    elif case == "two-frames":
        path = _rewritten(src, tmp_path / "r", T.POSES.name, _truth_messages(2))
    elif case == "all-lost":
        path = _rewritten(src, tmp_path / "r", T.POSES.name, _truth_messages(lose_all=True))
    elif case == "other-design":
        from ros_nodes import convert
        from ros_nodes.logic.mcap_append import NewMessage

        doc = json.loads((SAMPLE / "design.json").read_text())
        doc["nx"] = 10
        msg = NewMessage(T.RIG_DESIGN.name, 0, convert.serialize(convert.json_text(doc)))
        path = _rewritten(src, tmp_path / "r", T.RIG_DESIGN.name, [msg])
    elif case in ("cut-mcap", "cut-calibration"):  # a damaged copy of the run folder
        path = Path(shutil.copytree(SAMPLE, tmp_path / "r"))
        cut = path / ("recording.mcap" if case == "cut-mcap" else "calibration.json")
        cut.write_bytes(cut.read_bytes()[:cut.stat().st_size // 2])
    else:
        from ros_nodes.logic.mcap_append import append_messages

        (tmp_path / "r").mkdir()
        path = append_messages(src, tmp_path / "r" / "recording.mcap", {}, [],
                               replace=(T.IMAGE.name, T.CAMERA_INFO.name, T.GROUND_TRUTH.name))
    out = tmp_path / "out"
    code = compare_main([str(path), "--out", str(out), "-q", *SMALL_UNITS])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and message in err[0], err
    assert not (out / "summary.json").exists()  # no partial output presented as a result
