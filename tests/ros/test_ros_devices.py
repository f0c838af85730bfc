"""Shaker and stage lifecycle nodes, started for real as console scripts on an isolated domain."""

import time

import numpy as np
import pytest
from rostools import call, spin_until, stop_process


def start_shaker(start_node, tmp_path, parameters: str):
    """The shaker node with these YAML lines of parameters (indented under `ros__parameters`);
    the test's client node may command motion (by default only the sequencer)."""
    params = tmp_path / "shaker.yaml"
    params.write_text("shaker:\n  ros__parameters:\n    allowed_callers: [/test_client]\n"
                      + parameters)
    return start_node("metarig-shaker", "--params-file", str(params))


def test_shaker_refuses_out_of_limits_then_plays_a_pulse_and_stops(ros_node, start_node,
                                                                    tmp_path):
    from diagnostic_msgs.msg import DiagnosticArray
    from metarig_msgs.srv import FirePulse
    from sensor_msgs.msg import JointState
    from std_srvs.srv import Trigger
    from trajectory_msgs.msg import JointTrajectory

    from ros_nodes import topics as T
    from ros_nodes.nodes._common import COMMAND, LATCHED, qos_profile

    # a deep reader queue: a node that stalls under load catches up in a burst of samples
    deep = qos_profile(T.SHAKER_JOINTS.qos, depth=5000)
    proc = start_shaker(start_node, tmp_path, "    device:\n      max_amplitude_m: 0.008\n"
                                              "      max_duration_s: 60.0\n")
    node, ex = ros_node
    try:
        states, cmds, diags = [], [], []
        node.create_subscription(JointState, T.SHAKER_JOINTS.name, states.append, deep)
        node.create_subscription(DiagnosticArray, T.DIAGNOSTICS.name, diags.append, COMMAND)
        node.create_subscription(JointTrajectory, "/shaker/command", cmds.append, LATCHED)
        fire = node.create_client(FirePulse, "/shaker/fire")
        # the stream flows before any motion: a reader matched late (under load) would miss
        # the start of the pulse, the joint states being volatile
        spin_until(ex, lambda: states, 20.0, "the shaker's joint states")
        # the YAML limit (8 mm) is in force: 10 mm is refused with the reason
        r = call(fire, FirePulse.Request(waveform="pulse", amplitude_m=0.010, frequency_hz=30.0), ex)
        assert not r.accepted and "amplitude" in r.message and "0.008" in r.message
        r = call(fire, FirePulse.Request(waveform="pulse", amplitude_m=0.005, frequency_hz=500.0), ex)
        assert not r.accepted and "frequency" in r.message
        r = call(fire, FirePulse.Request(waveform="pulse", amplitude_m=0.0075, frequency_hz=30.0,
                                         delay_s=0.05), ex)
        assert r.accepted, r.message
        assert r.duration_s == pytest.approx(1 / 30)
        spin_until(ex, lambda: cmds, 30.0, "the latched commanded waveform")
        u = np.array([p.positions[0] for p in cmds[-1].points])
        assert u.max() == pytest.approx(0.0075, rel=1e-3) and u[0] == 0.0
        start = r.start.sec + 1e-9 * r.start.nanosec
        spin_until(ex, lambda: states and states[-1].header.stamp.sec + 1e-9 *
                   states[-1].header.stamp.nanosec > start + 0.06, 15.0, "the pulse to finish")
        x = np.array([m.position[0] for m in states])
        assert x.max() == pytest.approx(0.0075, rel=0.05)  # measured peak follows the command
        assert abs(x[-1]) < 2e-4
        # stop during a second waveform (a 50 s burst: a second request refused meanwhile): the
        # actuator returns to rest. A motion request is not repeated (no resend: the node has
        # answered before, and a repeat is not harmless). The burst outlasts any stall of a
        # loaded machine: a 7.5 s one had ended before the second request was taken, once.
        # The second request, refused while the burst plays, is repeated every 5 s: a repeat
        # is refused too, and one in CI went unanswered for 45 s
        t_fire = time.monotonic()
        r = call(fire, FirePulse.Request(waveform="burst", amplitude_m=0.002, frequency_hz=20.0,
                                         cycles=1000.0), ex, resend_s=45.0)
        assert r.accepted, r.message
        took = time.monotonic() - t_fire
        print(f"the 50 s burst was answered in {took:.2f} s")
        # its 100 000-point commanded waveform is built after the answer, off the device lock:
        # built inside the request, the answer (and any stop) waited 14-15 s beside four busy
        # loops, 0.06-0.07 s now
        assert took < 5.0
        r2 = call(fire, FirePulse.Request(waveform="pulse", amplitude_m=0.002, frequency_hz=20.0),
                  ex, resend_s=5.0)
        assert not r2.accepted and "already playing" in r2.message, r2.message
        assert call(node.create_client(Trigger, "/shaker/stop"), Trigger.Request(), ex).success

        def stamp(m):
            return m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec

        # the stop counts from when the node took it (its diagnostics stamp), not from when this
        # client sent it: a node without CPU for a while (load 9) takes it late, and the burst
        # rightly plays until then (a node stopped for 0.6 s by SIGSTOP took it 1.3 s late)
        def stopped():
            return [m for m in diags if m.status[0].message == "stopped (stop service)"]

        spin_until(ex, stopped, 30.0, "the node's stop diagnostics")
        t_stop = stamp(stopped()[0])
        # 20 joint states from 0.25 s after the stop on, however fast the node publishes them
        # (a node short of CPU in a loaded suite once published one in the 0.05 s after that)
        def late():
            return [m.position[0] for m in states if stamp(m) > t_stop + 0.25]

        spin_until(ex, lambda: len(late()) >= 20, 30.0, "20 joint states from 0.25 s after stop")
        assert np.abs(late()).max() < 1e-4
        # the burst's commanded waveform, built and published after the answer (off the lock
        # a stop takes), arrives whole: 50 s at the default 2 kHz, from the burst's start
        def burst():
            return [m for m in cmds if (m.header.stamp.sec, m.header.stamp.nanosec)
                    == (r.start.sec, r.start.nanosec)]

        spin_until(ex, burst, 60.0, "the burst's commanded waveform")
        u = np.array([p.positions[0] for p in burst()[-1].points])
        assert u.size == 100_001 and u.max() == pytest.approx(0.002, rel=1e-3)
    finally:
        print(stop_process(proc))


def test_a_shaker_behind_its_sampling_answers_and_stops_promptly(ros_node, start_node,
                                                                         tmp_path):
    """A node whose sampling timer is due again whenever it returns (10 kHz here; 1 kHz on a
    loaded machine) still answers its requests and its stop between sampling calls (the timer's
    own callback group, a bounded catch-up per call). In one callback group rclpy served the
    timer first: the second request waited until the 9 s burst had ended, and was accepted."""
    from metarig_msgs.srv import FirePulse
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState
    from std_srvs.srv import Trigger

    from ros_nodes import topics as T

    proc = start_shaker(start_node, tmp_path, "    rate_hz: 10000.0\n")
    node, ex = ros_node
    try:
        newest = []  # the newest joint state only: this client must not fall behind itself
        node.create_subscription(JointState, T.SHAKER_JOINTS.name, newest.append,
                                 QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT))
        spin_until(ex, lambda: newest, 20.0, "the shaker's joint states")
        fire = node.create_client(FirePulse, "/shaker/fire")
        r = call(fire, FirePulse.Request(waveform="burst", amplitude_m=0.002, frequency_hz=20.0,
                                         cycles=180.0), ex, resend_s=45.0)  # 9 s
        assert r.accepted, r.message
        t_end = time.monotonic() + 2.0
        spin_until(ex, lambda: time.monotonic() > t_end, 5.0, "2 s of the burst")
        m = newest[-1]
        lag = time.time() - (m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec)
        t0 = time.monotonic()
        r = call(fire, FirePulse.Request(waveform="pulse", amplitude_m=0.002, frequency_hz=20.0),
                 ex, timeout_s=15.0, resend_s=5.0)  # refused: a repeat is harmless
        assert not r.accepted and "already playing" in r.message, r.message
        assert call(node.create_client(Trigger, "/shaker/stop"), Trigger.Request(), ex,
                    timeout_s=15.0).success
        took = time.monotonic() - t0
        print(f"the node, its newest joint state {lag:.2f} s old, answered two requests in "
              f"{took:.2f} s")
        assert took < 5.0  # the burst lasts 9 s
    finally:
        print(stop_process(proc))

def test_stage_moves_holds_refuses_and_validates_parameters(ros_node, start_node):
    from metarig_msgs.srv import SetStrain
    from rcl_interfaces.msg import Parameter as ParamMsg
    from rcl_interfaces.msg import ParameterType, ParameterValue
    from rcl_interfaces.srv import SetParameters
    from sensor_msgs.msg import JointState
    from std_msgs.msg import String

    from ros_nodes import topics as T
    from ros_nodes.nodes._common import qos_profile

    proc = start_node("metarig-stage", "-p", "allowed_callers:=[/test_client]")
    node, ex = ros_node
    try:
        states, modes = [], []
        node.create_subscription(JointState, T.STAGE_JOINTS.name, states.append,
                                 qos_profile(T.STAGE_JOINTS.qos, depth=5000))
        # a reader queue of 10: with the latched topic's depth of 1, a client stalled for the
        # 0.08 s of the move would find "holding" only
        node.create_subscription(String, "/stage/state", lambda m: modes.append(m.data),
                                 qos_profile(T.STAGE_STATE.qos, depth=10))
        setp = node.create_client(SetStrain, "/stage/set_strain")
        r = call(setp, SetStrain.Request(strain=0.15), ex)
        assert not r.accepted and "strain 0.15 outside" in r.message
        r = call(setp, SetStrain.Request(strain=0.02), ex)
        assert r.accepted and r.eta_s == pytest.approx(0.08)
        spin_until(ex, lambda: modes and modes[-1] == "holding", 30.0, "stage holding")
        t_hold = time.time()  # the node runs on the system clock here
        assert "moving" in modes
        # a reader that fell behind under load first drains older states: wait for one taken
        # after the stage said it holds
        spin_until(ex, lambda: states and states[-1].header.stamp.sec + 1e-9 *
                   states[-1].header.stamp.nanosec > t_hold + 0.01, 5.0, "joint states")
        closing = states[-1].position[0] + states[-1].position[1]
        assert closing == pytest.approx(0.02 * 0.225, abs=1e-5)
        # parameters: an out-of-range value and an inconsistent pair are refused with a reason
        ps = node.create_client(SetParameters, "/stage/set_parameters")

        def set_param(name, value):
            p = ParamMsg(name=name, value=ParameterValue(type=ParameterType.PARAMETER_DOUBLE,
                                                         double_value=value))
            return call(ps, SetParameters.Request(parameters=[p]), ex).results[0]

        bad = set_param("device.max_strain", 0.9)
        assert not bad.successful and bad.reason
        bad = set_param("device.closing_speed_m_s", 0.5)  # 2.2/s strain rate > 0.25/s limit
        assert not bad.successful and "strain rate" in bad.reason
        assert set_param("device.max_strain", 0.05).successful
        r = call(setp, SetStrain.Request(strain=0.06), ex)
        assert not r.accepted and "0.05" in r.message
    finally:
        print(stop_process(proc))


def test_shaker_compensates_its_drive_and_the_measured_peak_error_drops(ros_node, start_node,
                                                                        tmp_path):
    """A resonant simulated actuator (80 Hz, damping 0.3) overshoots the paper's 7.5 mm pulse;
    `/shaker/compensate` iterates the drive against the shaker's sensor, and the same request
    fired again is measured (the joint states the node publishes) within 0.5 % of 7.5 mm."""
    from diagnostic_msgs.msg import DiagnosticArray
    from metarig_msgs.srv import FirePulse
    from sensor_msgs.msg import JointState

    from ros_nodes import topics as T
    from ros_nodes.nodes._common import COMMAND, qos_profile

    proc = start_shaker(start_node, tmp_path, "    device:\n      natural_frequency_hz: 80.0\n"
                                              "      damping_ratio: 0.3\n")
    node, ex = ros_node
    try:
        states, diags = [], []
        node.create_subscription(JointState, T.SHAKER_JOINTS.name, states.append,
                                 qos_profile(T.SHAKER_JOINTS.qos, depth=5000))
        node.create_subscription(DiagnosticArray, T.DIAGNOSTICS.name,
                                 lambda m: diags.extend(m.status), COMMAND)
        fire = node.create_client(FirePulse, T.SHAKER_FIRE.name)
        compensate = node.create_client(FirePulse, T.SHAKER_COMPENSATE.name)
        req = FirePulse.Request(waveform="pulse", amplitude_m=0.0075, frequency_hz=30.0,
                                delay_s=0.05)
        # the stream flows before the first pulse: a reader matched late (under load) missed
        # the start of its window (46 of the 72 joint states asked for, once)
        spin_until(ex, lambda: states, 20.0, "the shaker's joint states")

        def stamp(t):
            return t.sec + 1e-9 * t.nanosec

        def peak_error(r) -> float:
            """The measured peak over the drive and 30 ms after, against 7.5 mm."""
            t0, t1 = stamp(r.start), stamp(r.start) + r.duration_s + 0.03
            spin_until(ex, lambda: states and stamp(states[-1].header.stamp) > t1 + 0.01,
                       20.0, "the joint states of the pulse")
            x = [m.position[0] for m in states if t0 <= stamp(m.header.stamp) <= t1]
            assert len(x) > 0.9 * (t1 - t0) * 1000  # the node reads at 1 kHz
            return max(x) / 0.0075 - 1.0

        r = call(fire, req, ex)
        assert r.accepted and "compensated" not in r.message, r.message
        before = peak_error(r)
        assert 0.05 < before < 0.08  # the overshoot the lab saw: 7.9-8.7 mm for 7.5 mm
        spin_until(ex, lambda: any(s.message == "waveform finished" for s in diags), 10.0,
                   "the pulse to end")
        r = call(compensate, req, ex, resend_s=45.0)  # a motion request: never repeated
        assert r.accepted, r.message
        assert "measured by the simulated shaker's displacement sensor" in r.message
        spin_until(ex, lambda: any(s.message.startswith("compensation ") for s in diags),
                   60.0, "the compensation's outcome")
        done = next(s for s in diags if s.message.startswith("compensation "))
        assert done.message.startswith("compensation done: ") and "\n" not in done.message
        values = {kv.key: kv.value for kv in done.values}
        assert values["converged"] == "True"
        first = float(values["peak_errors"].strip("[]").split(",")[0])
        # the first drive is the request: the same overshoot, measured again. Each measured peak
        # is the largest of 1 kHz readings, which may fall up to (2 pi 30 Hz x 0.5 ms)^2 / 2 =
        # 0.44 % of the amplitude below the true peak (0.06145 then 0.06360 was seen under
        # load); a compensated first drive would be near 0, far outside this band
        assert first == pytest.approx(before, abs=0.005)
        r = call(fire, req, ex, resend_s=45.0)
        assert r.accepted and "compensated drive" in r.message, r.message
        after = peak_error(r)
        assert abs(after) <= 0.005 and abs(after) < abs(before) / 10, (before, after)
        print(f"measured peak error: {before:+.3%} as requested, {after:+.3%} compensated")
    finally:
        print(stop_process(proc))
