"""The function-generator shaker drive against a pyvisa-sim emulation of a Keysight 33522B
(devices/shaker/keysight33500b.yaml): the whole SCPI sequence for a pulse and a burst, the
settings and the uploaded waveform read back from the emulated instrument, refusals (limits
before the drive, volts before the instrument, another instrument), an instrument error
reported with its text, and stop turning the output off."""

import shutil
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pyvisa_sim", reason="pip install pyvisa pyvisa-sim")

import pyvisa  # noqa: E402

from devices.limits import LimitError  # noqa: E402
from devices.shaker.funcgen import (EMULATOR_RESOURCE, EMULATOR_YAML, FuncGenConfig,  # noqa: E402
                                    FunctionGeneratorShaker, InstrumentError, arb_upload)
from devices.shaker.port import ShakerDrive, prepare  # noqa: E402
from devices.shaker.waveform import WaveformRequest  # noqa: E402

# no watchdog: these tests compare the commands sent (the watchdog has its own tests)
CFG = FuncGenConfig(m_per_v=0.002, max_volts=5.0, sample_rate_hz=20e3, watchdog_s=0.0)
ARM = ["BURS:MODE TRIG", "BURS:NCYC 1", "TRIG:SOUR BUS", "BURS:STAT 1", "OUTP 1"]


class Spy:
    """Records what the driver writes to the instrument (commands, first 40 characters)."""

    def __init__(self, resource):
        self.sent: list[str] = []
        write = resource.write

        def spying(msg, *a, **kw):
            self.sent.append(msg[:40])
            return write(msg, *a, **kw)

        resource.write = spying


@pytest.fixture
def rm(tmp_path):
    """A resource manager on an emulated instrument of this test's own: pyvisa keeps one
    pyvisa-sim library (and so one instrument state) per device file and process, which a
    generator that another test of the same process left open (its watchdog still asking
    `SYST:ERR?`) would share, interleaving its queries with this test's read-backs."""
    own = tmp_path / Path(EMULATOR_YAML).name
    shutil.copyfile(EMULATOR_YAML, own)
    rm = pyvisa.ResourceManager(f"{own}@sim")
    yield rm
    rm.close()


@pytest.fixture
def drive(rm):
    d = FunctionGeneratorShaker(EMULATOR_RESOURCE, CFG, resource_manager=rm)
    d.spy = Spy(d._device)
    d.start(100.0)
    yield d
    d.close()


@pytest.fixture
def panel(rm):
    """A second session on the emulated instrument, as a user at its front panel would read it."""
    r = rm.open_resource(EMULATOR_RESOURCE, read_termination="\n", write_termination="\n")
    yield lambda q: r.query(q).strip()
    r.close()


def _commands(spy) -> list[str]:
    return [c for c in spy.sent if c != "SYST:ERR?"]


def test_pulse_uploaded_armed_triggered_and_read_back(drive, panel):
    assert isinstance(drive, ShakerDrive)
    assert "33522B" in drive.identity and "MY52400001" in drive.identity
    assert panel("OUTP:LOAD?") == "INF" and float(panel("VOLT:LIM:HIGH?")) == 5.0
    assert panel("VOLT:LIM:STAT?") == "1"
    wf = prepare(drive.limits, WaveformRequest("pulse", amplitude_m=0.0075, frequency_hz=30.0))
    drive.play(wf, start_s=100.0)          # start already due: triggered at once
    sent = _commands(drive.spy)
    assert sent[:4] == ["ABOR", "OUTP 0", "DATA:VOL:CLE",
                        "DATA:ARB METARIG,0.00000,0.00002,0.00009"]
    assert sent[4:10] == ["FUNC ARB", "FUNC:ARB METARIG", sent[6], "VOLT:OFFS 0", sent[8],
                          "BURS:MODE TRIG"]
    assert sent[9:14] == ARM and sent[14:] == ["*OPC?", "*TRG"]
    # every configuration command was followed by an error-queue read
    assert drive.spy.sent.count("SYST:ERR?") >= 14
    # the emulated instrument holds what a 7.5 mm pulse at 2 mm/V needs: 3.75 V peak
    assert panel("FUNC?") == "ARB" and panel("FUNC:ARB?") == "METARIG"
    assert float(panel("VOLT?")) == pytest.approx(7.5) and float(panel("VOLT:OFFS?")) == 0.0
    n = int(20e3 / 30.0) + 1
    assert float(panel("FUNC:ARB:SRAT?")) == pytest.approx((n - 1) * 30.0, rel=1e-6)
    assert panel("BURS:MODE?") == "TRIG" and panel("BURS:NCYC?") == "1"
    assert panel("TRIG:SOUR?") == "BUS" and panel("BURS:STAT?") == "1" and panel("OUTP?") == "1"
    name, *values = panel("DATA:ARB?").split(",")
    values = np.array(values, float)
    assert name == "METARIG" and values.size == n
    t = np.arange(n) / ((n - 1) * 30.0)
    np.testing.assert_allclose(values * 3.75, wf.displacement(t) / 0.002, atol=1e-4)
    assert values.max() == pytest.approx(1.0) and values[0] == 0.0 and values[-1] == 0.0
    # no sensor: read() is the commanded motion from the trigger on
    t0 = drive.started_s
    assert t0 == pytest.approx(100.0, abs=0.5)
    mid = drive.read(t0 + 0.5 / 30.0)
    assert mid.x_m == pytest.approx(0.0075) and mid.v_m_s == pytest.approx(0.0, abs=1e-9)
    assert drive.read(t0 + 1.0).x_m == 0.0


def test_burst_triggered_at_its_start_time(drive, panel):
    wf = prepare(drive.limits, WaveformRequest("burst", amplitude_m=0.004, frequency_hz=50.0,
                                               cycles=3))
    start = drive._clock() + drive._offset_s + 0.3
    drive.play(wf, start_s=start)
    assert "*TRG" not in drive.spy.sent and drive.started_s is None   # armed, waiting
    assert drive.read(start + 0.005).x_m == 0.0                         # nothing plays yet
    deadline = time.monotonic() + 5.0
    while drive.started_s is None and time.monotonic() < deadline:
        time.sleep(0.01)
    assert drive.spy.sent[-2:] == ["*TRG", "SYST:ERR?"] and drive.fault == ""
    assert drive.started_s == pytest.approx(start, abs=0.25)
    assert float(panel("VOLT?")) == pytest.approx(2 * 0.004 / 0.002, rel=1e-3)
    values = np.array(panel("DATA:ARB?").split(",")[1:], float)
    assert values.size == int(3 / 50.0 * 20e3) + 1
    assert values.min() == pytest.approx(-1.0, abs=1e-3) and values.max() == pytest.approx(1.0, abs=1e-3)
    r = drive.read(drive.started_s + 0.25 / 50.0)     # a quarter period: the crest
    assert r.x_m == pytest.approx(0.004) and abs(r.v_m_s) < 1e-6
    assert panel("OUTP?") == "1"


def test_stop_aborts_and_turns_the_output_off(drive, panel):
    wf = prepare(drive.limits, WaveformRequest("pulse", amplitude_m=0.005, frequency_hz=20.0))
    drive.play(wf, start_s=drive._clock() + drive._offset_s + 30.0)   # armed, far ahead
    assert panel("OUTP?") == "1"
    armed = drive._armed
    drive.stop()
    assert _commands(drive.spy)[-2:] == ["ABOR", "OUTP 0"] and panel("OUTP?") == "0"
    drive._trigger_later(armed)      # a timer that fired just as stop() ran: sends nothing
    time.sleep(0.05)
    assert "*TRG" not in drive.spy.sent and drive.read(drive.time_s + 1.0).x_m == 0.0
    drive.close()
    assert panel("OUTP?") == "0"


def test_limits_refuse_before_the_drive_is_called(drive):
    calls = []
    drive.play = lambda *a: calls.append(a)
    for req in (WaveformRequest("pulse", amplitude_m=0.02, frequency_hz=30.0),     # amplitude
                WaveformRequest("pulse", amplitude_m=0.005, frequency_hz=500.0),   # frequency
                WaveformRequest("burst", amplitude_m=0.01, frequency_hz=100.0)):   # velocity
        with pytest.raises(LimitError):
            drive.play(prepare(drive.limits, req), 0.0)
    assert calls == [] and drive.spy.sent == []


def test_volts_over_the_drive_limit_refused_before_upload(drive):
    cfg = FuncGenConfig(m_per_v=0.001, max_volts=5.0, sample_rate_hz=20e3)
    drive.reconfigure(cfg)
    drive.spy.sent.clear()
    wf = prepare(drive.limits, WaveformRequest("pulse", amplitude_m=0.0075, frequency_hz=30.0))
    with pytest.raises(LimitError, match=r"peak 7\.5 V exceeds the drive limit 5 V"):
        drive.play(wf, 0.0)
    assert drive.spy.sent == []
    with pytest.raises(LimitError, match="peak 7.5 V"):
        arb_upload(cfg, wf)


def test_instrument_error_reported_with_its_text(drive, panel):
    # 1 um at 2 mm/V is 1 mVpp: below the generator's 2 mVpp, refused by the instrument
    wf = prepare(drive.limits, WaveformRequest("pulse", amplitude_m=1e-6, frequency_hz=30.0))
    with pytest.raises(InstrumentError, match=r"refused 'VOLT 1\.0+e-03': -100,\"Command error\""):
        drive.play(wf, 0.0)
    assert "*TRG" not in drive.spy.sent and panel("SYST:ERR?") == '+0,"No error"'


def test_another_instrument_is_refused(tmp_path):
    yaml = tmp_path / "other.yaml"
    yaml.write_text(EMULATOR_YAML.read_text().replace(
        "Keysight Technologies,33522B,MY52400001", "Rigol Technologies,DG1022Z,DG1ZA0000001"))
    rm = pyvisa.ResourceManager(f"{yaml}@sim")
    with pytest.raises(InstrumentError, match=r"answers \*IDN\? with 'Rigol.*not a Keysight"):
        FunctionGeneratorShaker(EMULATOR_RESOURCE, CFG, resource_manager=rm)
    rm.close()


def test_long_waveform_fits_the_generator_memory():
    cfg = FuncGenConfig(sample_rate_hz=1e6, max_points=4096)
    wf = prepare(cfg, WaveformRequest("burst", amplitude_m=0.002, frequency_hz=10.0, cycles=20))
    up = arb_upload(cfg, wf)
    assert up.values.size == 4096 and up.sample_rate_hz == pytest.approx(4095 / 2.0)
    assert up.peak_v == pytest.approx(1.0, rel=1e-3)


def test_an_instrument_that_stops_answering_is_one_instrument_error(drive):
    from pyvisa.constants import StatusCode
    from pyvisa.errors import VisaIOError

    def silent(*a, **kw):
        raise VisaIOError(StatusCode.error_timeout)

    drive._device.write = silent
    wf = prepare(drive.limits, WaveformRequest("pulse", amplitude_m=0.005, frequency_hz=30.0))
    with pytest.raises(InstrumentError) as e:
        drive.play(wf, 0.0)
    assert str(e.value).startswith("Keysight Technologies 33522B serial MY52400001 did not take "
                                   "'ABOR': VI_ERROR_TMO") and "\n" not in str(e.value)
    assert e.value.__cause__ is None and drive.started_s is None
    drive._device.query = silent
    with pytest.raises(InstrumentError, match=r"did not answer 'VOLT:LIM:HIGH\?': VI_ERROR_TMO"):
        drive.query("VOLT:LIM:HIGH?")
    del drive._device.write, drive._device.query     # the emulator again, to close cleanly


def _armed_burst(drive):
    """A burst armed 30 s ahead: the output is on and waits for its trigger."""
    wf = prepare(drive.limits, WaveformRequest("burst", amplitude_m=0.004, frequency_hz=50.0,
                                               cycles=3))
    start = drive._clock() + drive._offset_s + 30.0
    drive.play(wf, start_s=start)
    return start


def _await_fault(drive, timeout_s=30.0):
    deadline = time.monotonic() + timeout_s
    while not drive.fault and time.monotonic() < deadline:
        time.sleep(0.01)
    return drive.fault


@pytest.fixture
def watched(rm):
    d = FunctionGeneratorShaker(EMULATOR_RESOURCE, FuncGenConfig(
        m_per_v=0.002, max_volts=5.0, sample_rate_hz=20e3, watchdog_s=0.05),
        resource_manager=rm)
    d.start(100.0)
    yield d
    d.close()


def test_the_watchdog_turns_the_output_off_on_an_instrument_error(watched, panel):
    start = _armed_burst(watched)
    assert panel("OUTP?") == "1" and watched.fault == ""
    time.sleep(0.2)                         # the watchdog finds nothing while all is well
    assert watched.fault == "" and panel("OUTP?") == "1"
    panel_write = watched._rm.open_resource(EMULATOR_RESOURCE, read_termination="\n",
                                            write_termination="\n")
    panel_write.write("SOUR:BOGUS 1")       # an error the instrument queues mid-run
    fault = _await_fault(watched)
    assert fault == ('Keysight Technologies 33522B serial MY52400001 reports -100,"Command '
                     'error"; output turned off')
    assert panel("OUTP?") == "0"            # not left armed: the trigger never comes either
    assert watched.read(start + 0.01).x_m == 0.0 and watched._timer is None
    # a new request clears the fault; the watchdog watches again
    _armed_burst(watched)
    assert watched.fault == "" and panel("OUTP?") == "1"


def test_the_watchdog_reports_a_generator_that_stops_answering(watched, panel):
    from pyvisa.constants import StatusCode
    from pyvisa.errors import VisaIOError

    _armed_burst(watched)
    sent = []

    def silent(msg, *a, **kw):              # the cable pulled: nothing gets through
        sent.append(msg)
        raise VisaIOError(StatusCode.error_timeout)

    watched._device.write = silent
    fault = _await_fault(watched)
    assert fault.startswith("Keysight Technologies 33522B serial MY52400001 did not answer "
                            "'SYST:ERR?': VI_ERROR_TMO") and "\n" not in fault
    # it tried to turn the output off, and says it may still be on
    assert sent[-2:] == ["ABOR", "OUTP 0"]
    assert "; the output may still be on: Keysight Technologies 33522B serial MY52400001 did " \
        "not take 'ABOR': VI_ERROR_TMO" in fault
    del watched._device.write
    assert panel("OUTP?") == "1"            # the emulator never heard OUTP 0: honestly said
    watched.stop()
    assert panel("OUTP?") == "0"
