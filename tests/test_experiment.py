"""The experiment procedure (`ros_nodes.logic.experiment`) against a fake rig: no ROS."""

import math

import pytest

from ros_nodes.logic.experiment import DEVICE_TOPICS, Experiment, RigError
from ros_nodes.logic.sequence import IMAGE_TOPIC, ExperimentPlan, Phase

STEP_S = 0.001  # simulated clock step of the fake rig, s


class FakeRig:
    """A `RigPort` on a fake wall clock: each `sleep` is one simulated clock step while the
    clock runs; the stage holds `eta_s` after a set-point, the camera films at `plan.fps`."""

    def __init__(self, plan: ExperimentPlan, *, eta_s=0.08, refuse_strain="", fault="",
                 design=True, lose_frames=0, problems=()):
        self.plan, self.eta_s, self.refuse_strain, self.fault = plan, eta_s, refuse_strain, fault
        self.problems = problems
        self.wall, self.sim, self.limit, self.running = 0.0, 0.0, math.inf, False
        self.calls: list[tuple] = []
        self._design = {"polygons_m": []} if design else None
        self._camera = {"state": "idle", "frames": 0}
        self._recorder: dict = {}
        self._stage, self._t_set, self._t_cam = "idle", None, None
        self.lose_frames = lose_frames
        self.unsubscribed: set[str] = set()  # device topics the recorder has not subscribed to
        self.shaker_fault_text, self.shaker_fault_at = "", math.inf
        self._compensated_at = math.inf
        self.compensation_outcome = (True, "compensation done: 3 drives (within the tolerances)")

    # time
    def now(self):
        return self.wall

    def sleep(self, dt_s):
        self.wall += dt_s
        if self.running and self.sim + STEP_S <= self.limit + 1e-12:
            self.sim = round(self.sim + STEP_S, 9)
        if self._t_set is not None and self.sim >= self._t_set + self.eta_s:
            self._stage = self.fault or "holding"

    def sim_time(self):
        return self.sim

    def announce(self, phase):
        self.calls.append(("announce", phase.value))

    def start_clock(self, until_s):
        self.limit = math.inf if until_s is None else round(until_s / STEP_S) * STEP_S
        self.running = True

    def clock_reached(self):
        return self.sim >= self.limit - 1e-12

    def pause_clock(self):
        self.running = False

    # status
    def service_names(self):
        return ("set_strain", "fire")

    def service_ready(self, name):
        return True

    def device_problems(self):
        return list(self.problems)

    def design(self):
        return self._design

    def camera(self):
        return self._camera

    def stage_state(self):
        return self._stage

    def shaker_fault(self):
        return self.shaker_fault_text if self.sim >= self.shaker_fault_at else ""

    def stage_hold_time(self):
        return None if self._stage != "holding" else round(self._t_set + self.eta_s, 9)

    def recorder(self):
        return self._recorder

    def recorder_subscribed(self, topics):
        return not self.unsubscribed & set(topics)

    # commands
    def set_strain(self, strain):
        self.calls.append(("set_strain", strain))
        if self.refuse_strain:
            return False, self.refuse_strain
        self._stage, self._t_set = "moving", self.sim
        return True, ""

    def fire(self, waveform, amplitude_m, frequency_hz, cycles, delay_s):
        self.calls.append(("fire", waveform, amplitude_m, frequency_hz, cycles, delay_s))
        return True, ""

    def compensate(self, waveform, amplitude_m, frequency_hz, cycles):
        self.calls.append(("compensate", self.sim, waveform, amplitude_m, frequency_hz, cycles))
        self._compensated_at = self.sim + 0.3  # the trial drives take simulated time
        return True, "compensating"

    def compensation(self):
        return self.compensation_outcome if self.sim >= self._compensated_at else None

    def camera_start(self, t_start_s):
        assert t_start_s == self.sim  # the capture starts at the time the clock holds
        self.calls.append(("camera_start", self.sim))
        self._t_cam = self.sim
        self._camera = {"state": "capturing", "frames": 0}
        return True

    def camera_snapshot(self):
        self.calls.append(("camera_snapshot", self.sim, self._stage))
        return True, ""

    def camera_stop(self):
        self.calls.append(("camera_stop", self.sim))
        n = self.plan.expected_frames(self._t_cam)
        self._camera = {"state": "done", "frames": n}
        self._recorder["counts"] = {IMAGE_TOPIC: n - self.lose_frames}
        self._recorder["last_stamp_s"] = {t: self.sim for t in DEVICE_TOPICS}

    def recorder_start(self):
        self.calls.append(("recorder_start",))
        self._recorder = {"recording": True, "matched": True, "counts": {}}

    def recorder_stop(self, timeout_s):
        self.calls.append(("recorder_stop",))
        return {"messages": 1, "dropped": 0}

    def stop_devices(self):
        self.calls.append(("stop_devices",))

    def names(self):
        return [c[0] for c in self.calls if c[0] != "announce"]


PLAN = ExperimentPlan(nx=4, ny=4, record_s=0.04, settle_s=0.01, fps=1000.0, timeout_s=5.0)


def test_runs_the_steps_in_order_on_simulated_time():
    rig = FakeRig(PLAN)
    exp = Experiment(PLAN, rig)
    timings = exp.run()
    assert rig.names() == ["camera_snapshot", "recorder_start", "set_strain", "camera_start",
                           "fire", "camera_stop"]
    snap = next(c for c in rig.calls if c[0] == "camera_snapshot")
    assert snap[1:] == (0.0, "idle")  # the reference image: before the stages move
    assert ("set_strain", PLAN.strain) in rig.calls
    fire = next(c for c in rig.calls if c[0] == "fire")
    assert fire[1:] == (PLAN.waveform, PLAN.amplitude_m, PLAN.frequency_hz, PLAN.cycles,
                        PLAN.pre_trigger_s)
    phases = dict(exp.events)
    assert [p for p, _ in exp.events] == ["starting", "precompress", "settle", "record", "pulse",
                                         "develop"]
    # settle starts once the stage holds; recording after settle_s; capture lasts record_s
    assert phases["settle"] == pytest.approx(0.081, abs=1.5e-3)
    assert phases["record"] == pytest.approx(phases["settle"] + PLAN.settle_s, abs=1e-9)
    assert phases["develop"] == pytest.approx(phases["record"] + PLAN.record_s, abs=1e-9)
    t_cam = next(c for c in rig.calls if c[0] == "camera_start")[1]
    assert t_cam == phases["record"]
    assert timings["frames"] == PLAN.expected_frames(t_cam) == 41
    assert set(timings) == {"startup", "precompress_settle", "record_live", "develop_publish",
                            "frames"}
    assert [c[1] for c in rig.calls if c[0] == "announce"] == [p for p, _ in exp.events]


def test_finish_stops_the_devices_before_closing_the_recording():
    rig = FakeRig(PLAN)
    exp = Experiment(PLAN, rig)
    exp.run()
    assert exp.finish(completed=True) == {"messages": 1, "dropped": 0}
    assert rig.names()[-2:] == ["stop_devices", "recorder_stop"]
    assert [p for p, _ in exp.events][-2:] == ["stop", "done"]
    assert not rig.running


def test_a_refused_strain_stops_the_run_with_the_reason():
    rig = FakeRig(PLAN, refuse_strain="strain 0.02 outside [0, 0.01]")
    exp = Experiment(PLAN, rig)
    with pytest.raises(RigError, match=r"stage: strain 0.02 outside"):
        exp.run()
    exp.finish(completed=False)
    assert rig.names() == ["camera_snapshot", "recorder_start", "set_strain", "stop_devices",
                           "recorder_stop"]
    assert [p for p, _ in exp.events] == ["starting", "precompress", "stop", "aborted"]


def test_a_stage_fault_during_precompression_is_an_error():
    rig = FakeRig(PLAN, fault="fault: encoder lost")
    with pytest.raises(RigError, match="stage fault: encoder lost"):
        Experiment(PLAN, rig).run()


def test_every_wait_has_a_deadline():
    rig = FakeRig(PLAN, design=False)  # the camera never builds the specimen
    with pytest.raises(RigError, match=r"timed out waiting for the specimen"):
        Experiment(PLAN, rig).run()
    assert rig.wall == pytest.approx(PLAN.timeout_s, abs=0.01)
    assert rig.names() == []  # nothing was commanded


def test_a_device_not_ready_stops_the_run_before_anything_moves():
    rig = FakeRig(PLAN, problems=["stage: the node is unconfigured, not active (its log says "
                                  "why)", "camera: cannot open the lab camera: no such serial"])
    with pytest.raises(RigError, match=r"^stage: the node is unconfigured.*; camera: cannot"):
        Experiment(PLAN, rig).run()
    assert rig.names() == []  # no snapshot, no recording, no motion


def test_a_long_wait_says_what_it_waits_for(caplog):
    import logging

    rig = FakeRig(PLAN, eta_s=0.5)  # 0.5 s of rig time: 2.5 s of wall time here
    with caplog.at_level(logging.INFO, logger="metarig.rig"):
        Experiment(PLAN, rig).run()
    notes = [r.getMessage() for r in caplog.records if r.getMessage().startswith("waiting")]
    assert notes == ["waiting 2 s for the stages to reach the strain (stage moving, camera idle "
                     "0 frames, 0 messages recorded)"]


def test_frames_missing_from_the_recording_are_reported_not_fatal(caplog):
    rig = FakeRig(PLAN, lose_frames=3)
    timings = Experiment(PLAN, rig).run()
    assert timings["frames"] == 41  # the camera's count; the summary compares it with the file
    assert "the recorder to write 41 frames" in caplog.text


def test_frames_a_real_camera_lost_go_into_the_timings():
    rig = FakeRig(PLAN)
    camera_stop = rig.camera_stop

    def stop_with_loss():  # a lab camera's status counts the frames its counter says it lost
        camera_stop()
        rig._camera.update(lost=2, received=41)

    rig.camera_stop = stop_with_loss
    timings = Experiment(PLAN, rig).run()
    assert timings["frames"] == 41 and timings["camera_lost"] == 2
    assert timings["camera_received"] == 41


def test_phase_values_are_the_published_names():
    assert [p.value for p in Phase][:6] == ["starting", "precompress", "settle", "record",
                                            "pulse", "develop"]


def test_device_motion_still_on_its_way_is_waited_for_then_reported(caplog):
    rig = FakeRig(PLAN)
    camera_stop = rig.camera_stop

    def late_stop():  # the shaker's samples reach the recorder only up to 0.1 s before the end
        camera_stop()
        rig._recorder["last_stamp_s"][DEVICE_TOPICS[0]] = rig.sim - 0.1

    rig.camera_stop = late_stop
    w0 = rig.wall
    timings = Experiment(PLAN, rig).run()
    assert "timed out waiting for the recorder to hold the shaker and stage motion" in caplog.text
    assert timings["frames"] == 41 and rig.wall - w0 > 30.0  # waited its 30 s, then went on


def test_a_device_that_fails_during_the_capture_ends_the_run_at_once():
    rig = FakeRig(PLAN)
    fire = rig.fire

    def fire_then_fault(*args):  # the stage controller stops answering after the pulse
        out = fire(*args)
        rig._stage = "fault: no reply from the stage controller on /dev/ttyUSB0"
        return out

    rig.fire = fire_then_fault
    exp = Experiment(PLAN, rig)
    with pytest.raises(RigError, match=r"^stage fault: no reply from the stage controller"):
        exp.run()
    assert rig.sim - dict(exp.events)["record"] < 0.005  # at once, not after record_s
    exp.finish(completed=False)
    assert [p for p, _ in exp.events][-4:] == ["record", "pulse", "stop", "aborted"]
    assert rig.names()[-2:] == ["stop_devices", "recorder_stop"]


def test_a_shaker_fault_during_the_capture_ends_the_run_with_its_line():
    rig = FakeRig(PLAN)
    fire = rig.fire
    why = 'fault: 33522B reports -100,"Command error"; output turned off'

    def fire_then_fault(*args):  # the generator's watchdog finds an error after the pulse
        out = fire(*args)
        rig.shaker_fault_text, rig.shaker_fault_at = why, rig.sim + 0.002
        return out

    rig.fire = fire_then_fault
    exp = Experiment(PLAN, rig)
    with pytest.raises(RigError) as e:
        exp.run()
    assert str(e.value) == "shaker " + why
    assert rig.sim - dict(exp.events)["record"] < 0.01  # at once, not after record_s
    exp.finish(completed=False)
    assert rig.names()[-2:] == ["stop_devices", "recorder_stop"]


def test_the_drive_is_compensated_before_the_recording_starts():
    plan = ExperimentPlan(**{**PLAN.as_dict(), "compensate": True})
    rig = FakeRig(plan)
    exp = Experiment(plan, rig)
    exp.run()
    assert rig.names()[:3] == ["compensate", "camera_snapshot", "recorder_start"]
    comp = next(c for c in rig.calls if c[0] == "compensate")
    assert comp[2:] == (plan.waveform, plan.amplitude_m, plan.frequency_hz, plan.cycles)
    phases = dict(exp.events)
    assert [p for p, _ in exp.events][:3] == ["starting", "compensate", "precompress"]
    assert phases["precompress"] >= phases["compensate"] + 0.3  # the clock ran the trials
    assert exp.compensation.startswith("compensation done")
    # a compensation that fails (a stop, readings missing) ends the run with its line
    rig = FakeRig(plan)
    rig.compensation_outcome = (False, "compensation failed: stopped before it ended")
    with pytest.raises(RigError, match="^shaker: compensation failed: stopped before it ended$"):
        Experiment(plan, rig).run()
    assert "set_strain" not in rig.names()


def test_the_recorder_subscribes_to_the_device_motion_before_it_starts():
    rig = FakeRig(PLAN)
    rig.unsubscribed = set(DEVICE_TOPICS[:1])  # the recorder has not discovered the shaker
    with pytest.raises(RigError, match="^timed out waiting for the recorder to subscribe to the "
                                       "shaker's and the stage's motion$"):
        Experiment(PLAN, rig).run()
    assert "recorder_start" not in rig.names() and "set_strain" not in rig.names()
    rig = FakeRig(PLAN)
    steps = iter(range(50))
    rig.unsubscribed = set(DEVICE_TOPICS)

    def subscribed_after_a_while(topics):  # DDS discovery takes its time
        if next(steps, None) is None:
            rig.unsubscribed = set()
        return not rig.unsubscribed & set(topics)

    rig.recorder_subscribed = subscribed_after_a_while
    assert Experiment(PLAN, rig).run()["frames"] == 41
    assert rig.names()[:2] == ["camera_snapshot", "recorder_start"]


def test_a_lab_camera_s_first_frame_comes_before_the_pulse():
    """On the system clock a lab camera may stream its first frame late (an emulator on a busy
    host took 117 ms): the pulse is fired only once a frame came, so the footage holds it."""

    class LateCamera(FakeRig):
        def camera_start(self, t_start_s):
            super().camera_start(t_start_s)
            self._camera = {"state": "streaming", "frames": 0}  # started, no frame yet
            self.first_frame_wall = self.wall + 0.2
            return True

        def camera(self):
            if self._camera.get("state") == "streaming" and self.wall >= self.first_frame_wall:
                self._camera = {"state": "streaming", "frames": 1}
            return self._camera

        def fire(self, *args):
            self.fired_wall = self.wall
            return super().fire(*args)

    rig = LateCamera(PLAN)
    Experiment(PLAN, rig).run()
    assert rig.fired_wall >= rig.first_frame_wall
    silent = LateCamera(PLAN)
    silent.first_frame_wall = math.inf
    silent.camera_start = lambda t: (FakeRig.camera_start(silent, t),
                                     setattr(silent, "_camera",
                                             {"state": "streaming", "frames": 0}))[0]
    with pytest.raises(RigError, match="the camera's first frame"):
        Experiment(PLAN, silent).run()
    assert "fire" not in silent.names()
