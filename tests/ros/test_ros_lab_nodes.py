"""The shaker and stage nodes with `hardware: lab`, in this process on the test's isolated domain:
the shaker drives the pyvisa-sim function generator of a lab file (a pulse uploaded and the
output on; volts over max_volts, an instrument error and a generator that stops answering
refused with the reason, the output left off), the stages move the Zaber emulator, and a lab device that cannot be opened leaves
the node unconfigured with one logged line, refusing requests."""

import pytest
from rostools import call, spin_until

pytest.importorskip("pyvisa_sim", reason="pip install pyvisa pyvisa-sim")

from devices.lab import EXAMPLE  # noqa: E402
from devices.stage.zaber_emulator import ZaberEmulator  # noqa: E402

FG = EXAMPLE.read_text().split("\n[stage]")[0]    # the format line and the [shaker] section


def _node(cls, ros_context, executor, lab, **params):
    from rclpy.parameter import Parameter

    overrides = [Parameter("hardware", value="lab"), Parameter("lab_file", value=str(lab)),
                 Parameter("allowed_callers", value=["/test_client"])]  # the test's client
    overrides += [Parameter(k, value=v) for k, v in params.items()]
    node = cls(context=ros_context, parameter_overrides=overrides)
    executor.add_node(node)
    return node


def _fire(node, ex, amplitude_m, frequency_hz=30.0):
    from metarig_msgs.srv import FirePulse

    client = node.create_client(FirePulse, "/shaker/fire")
    return call(client, FirePulse.Request(waveform="pulse", amplitude_m=amplitude_m,
                                          frequency_hz=frequency_hz), ex, timeout_s=20.0)


def test_shaker_plays_on_the_lab_function_generator_and_refuses_what_it_cannot(
        ros_context, ros_node, tmp_path):
    from devices.shaker.funcgen import FunctionGeneratorShaker
    from ros_nodes.nodes.shaker_node import ShakerNode

    lab = tmp_path / "lab.toml"
    lab.write_text(FG)
    client, ex = ros_node
    shaker = _node(ShakerNode, ros_context, ex, lab, rate_hz=50.0)
    try:
        drive = shaker._drive
        assert isinstance(drive, FunctionGeneratorShaker) and "33522B" in drive.identity
        r = _fire(client, ex, 0.0075)
        assert r.accepted, r.message
        # the emulated generator holds the pulse: 7.5 mm at 2 mm/V is 3.75 V peak, 7.5 Vpp
        assert float(drive.query("VOLT?")) == pytest.approx(7.5) and drive.query("OUTP?") == "1"
        spin_until(ex, lambda: shaker._playing_until is None, 30.0, "the pulse to end")
        # the lab file's limits, not the node's device.* ones (12 mm): 11 mm is refused
        r = _fire(client, ex, 0.011)
        assert not r.accepted and "outside the limits (0, 0.01] m" in r.message
        # an instrument error (1 um is 1 mVpp, below the generator's 2 mVpp): refused with the
        # instrument's reply, the drive stopped (output off)
        r = _fire(client, ex, 1e-6)
        assert not r.accepted and r.message.startswith("refused: ")
        assert "33522B serial MY52400001 refused 'VOLT " in r.message
        assert r.message.endswith('-100,"Command error"')
        assert drive.query("OUTP?") == "0" and shaker._playing_until is None
        # the node still serves: a good pulse after the refusal
        r = _fire(client, ex, 0.005)
        assert r.accepted, r.message
        spin_until(ex, lambda: shaker._playing_until is None, 30.0, "the pulse to end")
        # no drive compensation: the generator's readings are its command, not a measurement
        from metarig_msgs.srv import FirePulse

        r = call(client.create_client(FirePulse, "/shaker/compensate"),
                 FirePulse.Request(waveform="pulse", amplitude_m=0.005, frequency_hz=30.0), ex,
                 timeout_s=20.0)
        assert not r.accepted and r.message == (
            "refused: the drive measures nothing (its readings are the commanded motion, as a "
            "function generator's): nothing to compensate against")
    finally:
        ex.remove_node(shaker)
        shaker.destroy_node()


def test_volts_over_the_drive_limit_are_refused_before_the_generator_hears(
        ros_context, ros_node, tmp_path):
    from ros_nodes.nodes.shaker_node import ShakerNode

    lab = tmp_path / "lab.toml"
    lab.write_text(FG.replace("m_per_v = 0.002", "m_per_v = 0.001"))
    client, ex = ros_node
    shaker = _node(ShakerNode, ros_context, ex, lab, rate_hz=50.0)
    try:
        sent = []
        write = shaker._drive._device.write
        shaker._drive._device.write = lambda msg, *a, **kw: (sent.append(msg), write(msg, *a, **kw))
        r = _fire(client, ex, 0.0075)       # within the amplitude limit, but 7.5 V > 5 V
        assert not r.accepted and "peak 7.5 V exceeds the drive limit 5 V" in r.message
        assert sent == [] and shaker._drive.query("OUTP?") == "0"
    finally:
        ex.remove_node(shaker)
        shaker.destroy_node()


def test_a_generator_that_stops_answering_refuses_with_one_line(ros_context, ros_node,
                                                               tmp_path):
    from pyvisa.constants import StatusCode
    from pyvisa.errors import VisaIOError

    from ros_nodes.nodes.shaker_node import ShakerNode

    lab = tmp_path / "lab.toml"
    lab.write_text(FG)
    client, ex = ros_node
    shaker = _node(ShakerNode, ros_context, ex, lab, rate_hz=50.0)
    device = shaker._drive._device
    try:
        def silent(*a, **kw):
            raise VisaIOError(StatusCode.error_timeout)

        device.write = silent                 # a cable pulled: every command times out
        r = _fire(client, ex, 0.005)
        assert not r.accepted and "did not take 'ABOR': VI_ERROR_TMO" in r.message
        assert "\n" not in r.message and shaker._playing_until is None
        del device.write                      # back: the node still serves
        r = _fire(client, ex, 0.005)
        assert r.accepted, r.message
    finally:
        ex.remove_node(shaker)
        shaker.destroy_node()


def test_stages_move_the_zaber_emulator_of_a_lab_file(ros_context, ros_node, tmp_path):
    from metarig_msgs.srv import SetStrain

    from devices.stage.zaber import ZaberStages
    from ros_nodes.nodes.stage_node import StageNode

    client, ex = ros_node
    with ZaberEmulator() as emu:
        lab = tmp_path / "lab.toml"
        lab.write_text(f'[stage]\ndriver = "zaber"\nport = "{emu.port}"\nmicrostep_m = 1e-6\n'
                       "sample_height_m = 0.2\nmax_strain = 0.05\nclosing_speed_m_s = 0.02\n")
        stage = _node(StageNode, ros_context, ex, lab, rate_hz=20.0)
        try:
            assert isinstance(stage._stages, ZaberStages)
            set_strain = client.create_client(SetStrain, "/stage/set_strain")
            r = call(set_strain, SetStrain.Request(strain=0.08), ex, timeout_s=20.0)
            assert not r.accepted and "outside the limits [0, 0.05]" in r.message
            r = call(set_strain, SetStrain.Request(strain=0.01), ex, timeout_s=20.0)
            assert r.accepted, r.message
            # 0.01 x 0.2 m = 2 mm closing: each stage 1 mm, 1000 microsteps
            spin_until(ex, lambda: emu.position(1, 1) == 1000 and emu.position(2, 1) == 1000
                       and stage._stages.status.mode.value == "holding", 30.0,
                       "the stages to hold at 2 mm closing")
            assert "/1 1 move abs 1000" in emu.received and "/2 1 move abs 1000" in emu.received
        finally:
            ex.remove_node(stage)
            stage.destroy_node()


def test_a_lab_device_that_cannot_be_opened_leaves_the_node_unconfigured(
        ros_context, ros_node, tmp_path):
    from metarig_msgs.srv import SetStrain

    from ros_nodes.nodes.stage_node import StageNode

    lab = tmp_path / "lab.toml"
    lab.write_text('[stage]\ndriver = "zaber"\nport = "/dev/ttyNOSUCH0"\n')
    client, ex = ros_node
    stage = _node(StageNode, ros_context, ex, lab)
    try:
        assert stage._stages is None and not stage._active and stage._pubs == {}
        r = call(client.create_client(SetStrain, "/stage/set_strain"),
                 SetStrain.Request(strain=0.01), ex, timeout_s=20.0)
        assert not r.accepted and "not active" in r.message
    finally:
        ex.remove_node(stage)
        stage.destroy_node()
