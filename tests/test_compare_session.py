"""The comparison node's session logic without ROS: fed the sample recording's topics as the node
hears them, it gives the metrics of `metarig compare --poses truth`; impossible comparisons are
refused with one line; the automatic trigger fires once per experiment."""

import json
from pathlib import Path
from types import SimpleNamespace

import pytest

from ros_nodes import topics as T
from ros_nodes.recorded_compare import compare_recording
from ros_nodes.logic import comparison_run as run
from ros_nodes.logic.compare_session import CompareSession
from ros_nodes.logic.comparison_run import SUMMARY_KEYS, CompareError
from ros_nodes.logic.recording import stamp_s, total_closing_m

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "recordings" / "precompression-12x8"
MCAP = SAMPLE / "recording.mcap"


def recorded_messages(path: Path = MCAP) -> list[tuple[str, int, object]]:
    """(topic, log time ns, decoded message) of the recording in log-time order (`mcap_ros2`,
    as `ros_nodes.logic.recording` decodes it)."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    wanted = [T.RIG_DESIGN.name, T.RIG_CONFIG.name, T.RIG_PHASE.name, T.SHAKER_JOINTS.name,
              T.STAGE_JOINTS.name, T.STAGE_STATE.name, T.GROUND_TRUTH.name]
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        return [(ch.topic, rec.log_time, msg) for _s, ch, rec, msg
                in reader.iter_decoded_messages(topics=wanted, log_time_order=True)]


def feed(session: CompareSession, messages, design: bool = True, poses=None) -> None:
    """What the node does with each message; the ground truth stands in for `/dic/poses`."""
    for topic, log_ns, msg in messages:
        if topic == T.RIG_DESIGN.name and design:
            session.set_design(msg.data)
        elif topic == T.RIG_CONFIG.name:
            session.set_config(msg.data)
        elif topic == T.SHAKER_JOINTS.name and len(msg.position):
            session.add_shaker(stamp_s(msg), float(msg.position[0]))
        elif topic == T.STAGE_JOINTS.name and len(msg.position):
            session.add_stage(stamp_s(msg), total_closing_m(msg.position))
        elif topic == T.STAGE_STATE.name:
            session.stage_state(msg.data, log_ns * 1e-9)
        elif topic == T.GROUND_TRUTH.name and poses is None:
            session.add_poses(msg)
    for msg in poses or ():
        session.add_poses(msg)


@pytest.fixture(scope="module")
def messages():
    return recorded_messages()


@pytest.fixture(scope="module")
def offline(tmp_path_factory):
    return compare_recording(SAMPLE, tmp_path_factory.mktemp("offline"), poses="truth")


@pytest.fixture(scope="module")
def live(messages):
    session = CompareSession()
    feed(session, messages)
    return session.compare()


def test_the_session_gives_the_offline_metrics(live, offline):
    s = live.summary
    assert list(s)[: len(SUMMARY_KEYS)] == list(SUMMARY_KEYS)
    for key in SUMMARY_KEYS + ("energy_map_correlation", "target_peak_ke_exp_J",
                               "precompression_m", "units_compared"):
        assert s[key] == pytest.approx(offline[key], rel=1e-9, abs=1e-15), key
    for key in ("input_source", "frames", "scene", "n_units"):
        assert s[key] == offline[key], key
    assert s["frames"] == 51 and s["poses"] == T.POSES.name and s["recording"] == "live"
    assert set(offline) - {"mcap", "rrd", "timings_s"} == set(s)
    assert live.poses.n_t == 51 and live.reference_m.shape == (96, 2)


def test_the_messages_carry_the_result(live):
    from ros_nodes import convert

    msgs = convert.comparison_messages(live.ec, live.summary, live.reference_m)
    by_topic = {}
    for topic, _ns, msg in msgs:
        by_topic.setdefault(topic, []).append(msg)
    assert len(by_topic[T.COMPARE_SIMULATED.name]) == 51
    (result,) = by_topic[T.COMPARE_RESULT.name]
    assert result.velocity_nrmse == live.summary["velocity_nrmse"]
    (diag,) = by_topic[T.DIAGNOSTICS.name]
    assert diag.status[0].name == "comparison" and diag.status[0].level == b"\x00"
    assert json.loads(by_topic[T.COMPARE_SUMMARY.name][0].data)["frames"] == 51


def test_the_run_files_are_written(live, tmp_path):
    rrd = run.write_run_files(tmp_path, live.scene, live.polygons, live.poses, live.ec)
    run.write_summary(tmp_path, live.summary)
    assert rrd == tmp_path / "comparison.rrd" and rrd.stat().st_size > 0
    assert json.loads((tmp_path / "summary.json").read_text())["frames"] == 51
    assert (tmp_path / "velocity_maps.png").read_bytes()[:4] == b"\x89PNG"


def _refusal(session: CompareSession) -> str:
    with pytest.raises(CompareError) as err:
        session.compare()
    text = str(err.value)
    assert text and "\n" not in text
    return text


def test_impossible_comparisons_are_refused_with_one_line(messages):
    truth = [m for topic, _ns, m in messages if topic == T.GROUND_TRUTH.name]
    s = CompareSession()
    feed(s, messages, design=False)
    assert "no design received on /rig/design" in _refusal(s)
    assert s.refusal() == _refusal(s)

    s = CompareSession()
    feed(s, messages, poses=[])  # design, devices, no poses
    assert _refusal(s) == "no poses received on /dic/poses"

    s = CompareSession()
    feed(s, messages, poses=truth[:2])
    assert "only 2 frames" in _refusal(s) and "3 or more" in _refusal(s)
    s = CompareSession(min_frames=60)
    feed(s, messages)
    assert "only 51 frames" in _refusal(s) and "60 or more" in _refusal(s)

    lost = [SimpleNamespace(header=m.header, ids=m.ids, x=m.x, y=m.y, theta=m.theta,
                            quality=m.quality, lost=[True] * len(m.ids)) for m in truth]
    s = CompareSession()
    feed(s, messages, poses=lost)
    assert "every unit was lost in every frame" in _refusal(s)

    design = json.loads(next(m.data for topic, _ns, m in messages if topic == T.RIG_DESIGN.name))
    s = CompareSession()
    feed(s, messages)
    s.set_design({**design, "nx": 6})  # outlines of 96 units, a scene of 48
    assert "the design does not match" in _refusal(s)
    s.set_design({k: v for k, v in design.items() if k != "polygons_m"} | {"nx": 6})
    assert "do not match the design" in _refusal(s)
    s.set_design({"polygons_m": []})
    assert "lacks the scene" in _refusal(s)
    with pytest.raises(CompareError):
        s.set_design("{not json")


def test_the_automatic_comparison_fires_once_per_experiment(messages):
    s = CompareSession()
    assert not s.phase("stop")  # nothing heard yet
    feed(s, messages)
    assert s.phase("record") is False
    assert s.phase("stop") is True and s.phase("done") is False
    assert s.phase("starting") is False and s.n_frames == 0 and s.has_design
