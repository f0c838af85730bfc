"""The run summary's frame accounting, the plan's frame count, and the rig command's refusal of
empty or contradicting flags (pure logic, no ROS)."""

import pytest

from ros_nodes import topics as T
from ros_nodes.logic.sequence import ExperimentPlan, summary


def _report(recorded: int, dropped: int = 0) -> dict:
    return {"messages": recorded, "dropped": dropped,
            "topics": {T.IMAGE.name: {"count": recorded, "missing_by_sequence": dropped}}}


def test_trailing_frames_missing_from_the_recording_are_counted_as_lost():
    # 3 frames never reached the file and left no gap (they were last): only the published
    # count reveals them
    s = summary(ExperimentPlan(), {}, _report(97), {"frames": 100}, [], "completed")
    assert s["frames"] == {"published": 100, "recorded": 97, "lost": 3}


def test_frames_a_real_camera_lost_are_counted_beside_those_missing_from_the_file():
    # the camera's frame counter jumped by 3 (never published); the simulated camera has none
    s = summary(ExperimentPlan(), {}, _report(97), {"frames": 98, "camera_lost": 3,
                                                    "camera_received": 98}, [], "completed")
    assert s["frames"] == {"published": 98, "recorded": 97, "lost": 1, "lost_at_camera": 3,
                           "received_at_camera": 98}
    s = summary(ExperimentPlan(), {}, _report(98), {"frames": 98}, [], "completed")
    assert "lost_at_camera" not in s["frames"]


def test_complete_recording_has_no_lost_frames_and_no_report_means_no_frame_section():
    s = summary(ExperimentPlan(), {}, _report(100), {"frames": 100}, [], "completed")
    assert s["frames"]["lost"] == 0
    assert "frames" not in summary(ExperimentPlan(), {}, None, {"frames": 100}, [], "failed")


@pytest.mark.parametrize("t_start, expected", [(0.0, 100), (0.0205, 100), (0.02, 101)])
def test_expected_frames_counts_the_multiples_of_the_period_inside_the_window(t_start, expected):
    # frames at k / fps with t_start <= k / fps <= t_start + record_s, k >= 1
    assert ExperimentPlan(record_s=0.1, fps=1000.0).expected_frames(t_start) == expected


@pytest.mark.parametrize("args, message", [
    (["--design", ""], "--design is empty"),  # was the periodic design, silently
    (["--material", " "], "--material is empty"),  # was the default material, silently
    (["--nx", "10", "--design", "DESIGN"],  # --nx was dropped, silently
     "--nx/--ny disagree with the design file's lattice 8x6"),
])
def test_the_rig_refuses_empty_or_contradicting_flags_before_it_starts(tmp_path, capsys, args,
                                                                       message):
    from design_engine.design.design_io import save_design
    from design_engine.physics.lattice import periodic_design, quads
    from ros_nodes.cli_rig import rig_main

    design = save_design(tmp_path / "d.json", quads(8, 6), periodic_design(quads(8, 6), 0.4))
    out = tmp_path / "run"
    argv = [str(design) if a == "DESIGN" else a for a in args]
    assert rig_main([*argv, "--out", str(out), "--no-compare"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"metarig rig: {message}") and not out.exists()
    with pytest.raises(SystemExit) as e:  # 0 workers was every core, silently
        rig_main(["--workers", "0", "--out", str(out)])
    assert e.value.code == 2 and "argument --workers: must be at least 1, got 0" in \
        capsys.readouterr().err


def test_the_frames_the_plan_expects_are_recorded_beside_those_published():
    # the capture window from the record phase: 0.1 s at 1 kHz from t = 0.222 s holds 101 frames;
    # a camera whose clock lagged at its start publishes more, which the summary keeps visible
    events = [("starting", 0.0), ("record", 0.222), ("develop", 0.322)]
    s = summary(ExperimentPlan(), {}, _report(103), {"frames": 103}, events, "completed")
    assert s["frames"] == {"published": 103, "recorded": 103, "lost": 0, "expected": 101}
