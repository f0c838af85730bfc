"""The main job (`make demo` = `metarig demo`): the run folder read back by independent readers."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo") / "run"
    env = dict(os.environ, PYTHONUNBUFFERED="1")  # the isolated domain of tests/ros/conftest
    r = subprocess.run([sys.executable, "-m", "metarig", "demo", "--out", str(out)],
                       capture_output=True, text=True, timeout=600, env=env)
    assert r.returncode == 0, r.stderr[-3000:]
    return out, r.stdout


def test_the_report_says_where_what_and_how_long(demo):
    out, stdout = demo
    assert f"-> {out}" in stdout and f"rerun {out}/comparison.rrd" in stdout
    report = json.loads((out / "demo.json").read_text())
    d = report["design"]
    assert d["objective_after_J"] > d["objective_before_J"] > 0  # the design loop improved it
    assert set(report["timings_s"]) >= {"design", "export", "rig", "total"}
    assert report["comparison"]["lost_units"] == 0


def test_the_run_folder_reads_back(demo):
    out, _ = demo
    from rerun.chunk import RrdReader
    from rosbags.highlevel import AnyReader
    from svgelements import SVG

    from ros_nodes import topics as T

    with AnyReader([out / "recording.mcap"]) as reader:
        topics = {c.topic for c in reader.connections}
    assert {T.IMAGE.name, T.POSES.name, T.COMPARE_RESULT.name, T.IMAGE_PREVIEW.name} <= topics
    paths = {str(c.entity_path) for c in RrdReader(str(out / "comparison.rrd")).store().stream()}
    assert "/experiment/units" in paths and "/simulation/units" in paths
    shapes = [e for e in SVG.parse(str(out / "design.svg")).elements() if hasattr(e, "points")]
    assert len(shapes) >= 48  # one outline per unit of the 8x6 design
    summary = json.loads((out / "summary.json").read_text())
    assert np.isfinite(summary["velocity_nrmse"]) and summary["n_units"] == 48
    for png in ("velocity_maps.png", "target_ke.png", "row_peak_ke.png", "tracking_quality.png"):
        assert (out / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    design = json.loads((out / "design" / "design.json").read_text())
    assert design["format"] == "metarig-design/1" and design["feasible"]
