"""The comparison node for real (`metarig-compare` over DDS): the sample recording's topics
re-published (ground truth on /dic/poses), `/compare/run`, and the result of
`metarig compare --poses truth`; a comparison without poses is refused with one line."""

import json
from pathlib import Path

import pytest
from rostools import call, spin_until, stop_process, wait_matched

from ros_nodes import topics as T

ROOT = Path(__file__).resolve().parents[2]
SAMPLE = ROOT / "recordings" / "precompression-12x8"
NODE = "metarig-compare"
# recorded topic -> topic it is re-published on (the ground truth stands in for tracked poses)
REPLAY = {T.RIG_DESIGN.name: T.RIG_DESIGN, T.RIG_CONFIG.name: T.RIG_CONFIG,
          T.STAGE_STATE.name: T.STAGE_STATE, T.SHAKER_JOINTS.name: T.SHAKER_JOINTS,
          T.STAGE_JOINTS.name: T.STAGE_JOINTS, T.GROUND_TRUTH.name: T.POSES}


def _as(cls, decoded):
    """An rclpy message of today's `cls` with the fields of a message decoded by its recorded
    schema (fields added since the recording keep their defaults: the sample recordings predate
    the pose standard errors, so their CDR is not today's)."""
    out = cls()
    for name, kind in cls.get_fields_and_field_types().items():
        if not hasattr(decoded, name):
            continue
        value = getattr(decoded, name)
        if "/" in kind and not kind.startswith("sequence"):
            value = _as(type(getattr(out, name)), value)
        setattr(out, name, value)
    return out


def recorded(path: Path = SAMPLE / "recording.mcap") -> list[tuple[str, int, object]]:
    """(topic to publish on, log time ns, rclpy message) rebuilt from the recording."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    from ros_nodes.convert import message_class

    out = []
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _s, ch, msg, decoded in reader.iter_decoded_messages(topics=list(REPLAY),
                                                                  log_time_order=True):
            topic = REPLAY[ch.topic]
            out.append((topic.name, msg.log_time, _as(message_class(topic.type), decoded)))
    return out


def _statuses(got, name="comparison"):
    return [s for m in got for s in m.status if s.name == name]


def _publishers(node):
    from ros_nodes.convert import message_class
    from ros_nodes.nodes._common import qos_profile

    return {t.name: node.create_publisher(message_class(t.type), t.name, qos_profile(t.qos))
            for t in REPLAY.values()}


def test_the_node_compares_the_replayed_recording_like_the_offline_tool(
        ros_node, start_node, tmp_path):
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
    from metarig_msgs.msg import ComparisonResult, UnitPose2DArray
    from rclpy.duration import Duration
    from rosgraph_msgs.msg import Clock
    from std_msgs.msg import String
    from std_srvs.srv import Trigger

    from ros_nodes import convert
    from ros_nodes.recorded_compare import compare_recording
    from ros_nodes.nodes._common import COMMAND, LATCHED, STREAM, qos_profile

    node, ex = ros_node
    msgs = recorded()
    pubs = _publishers(node)
    clock = node.create_publisher(Clock, T.CLOCK.name, qos_profile(T.CLOCK_QOS))
    results, summaries, diags, simulated = [], [], [], []
    subs = [node.create_subscription(ComparisonResult, T.COMPARE_RESULT.name, results.append,
                                     LATCHED),
            node.create_subscription(String, T.COMPARE_SUMMARY.name, summaries.append, LATCHED),
            node.create_subscription(DiagnosticArray, T.DIAGNOSTICS.name, diags.append, COMMAND),
            node.create_subscription(UnitPose2DArray, T.COMPARE_SIMULATED.name,
                                     simulated.append, STREAM)]
    # rig time under /clock: the stages' `holding` is stamped at receipt, as the recorder did
    out_dir = tmp_path / "live"
    proc = start_node(NODE, "-p", "use_sim_time:=true", "-p", "auto:=false",
                      "-p", f"out_dir:={out_dir}")
    try:
        for p in (*pubs.values(), clock, *subs):
            wait_matched(p, ex, timeout_s=30)
        for topic, log_ns, msg in msgs:
            if topic == T.STAGE_STATE.name:  # the node's clock first, then the state
                for _ in range(5):
                    clock.publish(convert.clock(log_ns))
                    ex.spin_once(timeout_sec=0.1)
            pubs[topic].publish(msg)
        for p in pubs.values():
            assert p.wait_for_all_acked(Duration(seconds=10))
        for _ in range(5):
            ex.spin_once(timeout_sec=0.1)
        res = call(node.create_client(Trigger, T.COMPARE_RUN.name), Trigger.Request(), ex)
        assert res.success and "51 frames" in res.message, res.message
        offline = compare_recording(SAMPLE, tmp_path / "offline", poses="truth")
        spin_until(ex, lambda: results and summaries and _statuses(diags)
                   and len(simulated) >= 51, 60,
                   "the comparison result")
        spin_until(ex, lambda: (out_dir / "summary.json").exists(), 60, "summary.json")
    finally:
        out = stop_process(proc)
    r = results[-1]
    assert r.velocity_nrmse == pytest.approx(offline["velocity_nrmse"], abs=1e-6), out
    assert r.energy_map_correlation == pytest.approx(offline["energy_map_correlation"],
                                                     abs=1e-6)
    assert r.lost_units == 0 and r.units_compared == 96 and r.input_source == "tracked"
    assert len(r.t) == len(r.target_ke_exp) == len(r.velocity_error) > 0
    summary = json.loads(summaries[-1].data)
    assert summary["frames"] == 51 and summary["poses"] == T.POSES.name
    (status,) = _statuses(diags)
    assert status.level == DiagnosticStatus.OK, status.message
    values = {kv.key: kv.value for kv in status.values}
    assert float(values["velocity_nrmse"]) == pytest.approx(r.velocity_nrmse, rel=1e-9)
    assert len(simulated) == 51 and len(simulated[0].ids) == 96
    written = json.loads((out_dir / "summary.json").read_text())
    assert written["velocity_nrmse"] == summary["velocity_nrmse"]
    assert Path(written["rrd"]) == out_dir / "comparison.rrd"
    assert (out_dir / "comparison.rrd").stat().st_size > 0
    assert (out_dir / "velocity_maps.png").read_bytes()[:4] == b"\x89PNG"
    assert "Traceback" not in out, out


def test_a_comparison_without_poses_is_refused_with_one_line(ros_node, start_node):
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
    from rclpy.duration import Duration
    from std_srvs.srv import Trigger

    from ros_nodes.nodes._common import COMMAND

    node, ex = ros_node
    design = next(m for topic, _ns, m in recorded() if topic == T.RIG_DESIGN.name)
    pub = _publishers(node)[T.RIG_DESIGN.name]
    diags = []
    sub = node.create_subscription(DiagnosticArray, T.DIAGNOSTICS.name, diags.append, COMMAND)
    proc = start_node(NODE)
    try:
        wait_matched(pub, ex, timeout_s=30)
        wait_matched(sub, ex, timeout_s=30)
        pub.publish(design)
        assert pub.wait_for_all_acked(Duration(seconds=10))
        for _ in range(3):
            ex.spin_once(timeout_sec=0.1)
        client = node.create_client(Trigger, T.COMPARE_RUN.name)
        for k in (1, 2):  # refused, and still answering
            res = call(client, Trigger.Request(), ex)
            assert not res.success and res.message == "no poses received on /dic/poses"
            spin_until(ex, lambda k=k: len(_statuses(diags)) >= k, 30, "the error status")
        assert proc.poll() is None
    finally:
        out = stop_process(proc)
    for status in _statuses(diags):
        assert status.level == DiagnosticStatus.ERROR
        assert status.message == "no poses received on /dic/poses" and "\n" not in status.message
    assert "Traceback" not in out, out
