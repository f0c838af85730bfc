"""The Zaber stage driver against the protocol emulator on a pseudo-terminal: move to a strain
and hold with the positions read back, stop mid-move holds, a strain over the limits refused
before a byte is written, a jam (stalled and busy: the deadline; or a fault flag) and a silent
controller each a FAULT with one reason within a bounded time, reset after a fault."""

import time

import pytest

pytest.importorskip("serial", reason="pip install pyserial")

from devices.limits import LimitError  # noqa: E402
from devices.stage.port import StageCommand, StageMode, StagePair  # noqa: E402
from devices.stage.zaber import (SPEED_UNIT, StageControllerError, ZaberConfig,  # noqa: E402
                                 ZaberStages)

STEP = 1e-6            # microstep, m: round numbers below
CFG = ZaberConfig(sample_height_m=0.2, max_strain=0.05, microstep_m=STEP,
                  closing_speed_m_s=0.02, eta_factor=1.5, eta_margin_s=0.2, reply_timeout_s=0.1,
                  bottom_zero_steps=1000, top_zero_steps=500)


@pytest.fixture
def stages(emu):
    emu.set_position(1, 1, 1000)                              # both at zero closing
    emu.set_position(2, 1, 500)
    s = ZaberStages(emu.port, CFG)
    s.clock0 = time.monotonic()
    s.start(0.0)
    yield s
    s.close()


def _now(stages) -> float:
    return time.monotonic() - stages.clock0


def _read_until(stages, done, limit_s=5.0, period_s=0.02):
    end = time.monotonic() + limit_s
    while True:
        r = stages.read(_now(stages))
        if done(r) or time.monotonic() > end:
            return r
        time.sleep(period_s)


def test_move_to_a_strain_and_hold(stages, emu):
    assert isinstance(stages, StagePair)
    # the speed set on both controllers: each stage half the closing speed
    assert emu.received[:2] == [f"/1 1 set maxspeed {int(0.01 / STEP * SPEED_UNIT)}",
                                f"/2 1 set maxspeed {int(0.01 / STEP * SPEED_UNIT)}"]
    assert stages.eta_s(0.02) == pytest.approx(0.004 / 0.02)
    stages.command(StageCommand(target_strain=0.02))          # 4 mm closing: 0.2 s
    r = stages.read(_now(stages))
    assert r.mode == StageMode.MOVING and r.target_strain == pytest.approx(0.02)
    assert "/1 1 move abs 3000" in emu.received and "/2 1 move abs 2500" in emu.received
    r = _read_until(stages, lambda r: r.mode != StageMode.MOVING)
    assert r.mode == StageMode.HOLDING and stages.status.fault == ""
    assert r.bottom_m == pytest.approx(0.002) and r.top_m == pytest.approx(0.002)
    assert r.closing_m == pytest.approx(0.004)
    assert emu.position(1, 1) == 3000 and emu.position(2, 1) == 2500
    time.sleep(0.1)
    r = stages.read(_now(stages))                              # holds
    assert r.mode == StageMode.HOLDING and r.closing_m == pytest.approx(0.004)
    assert stages.status.closing_m == pytest.approx(0.004) and stages.eta_s(0.02) == 0.0


def test_stop_mid_move_holds_where_it_is(stages, emu):
    stages.command(StageCommand(target_strain=0.05))           # 10 mm: 0.5 s
    stages.read(_now(stages))
    time.sleep(0.15)
    stages.command(StageCommand(stop=True))
    r = stages.read(_now(stages))
    assert r.mode == StageMode.HOLDING and 0.0005 < r.closing_m < 0.009
    assert r.target_strain == pytest.approx(r.closing_m / 0.2)
    held = r.closing_m
    time.sleep(0.3)
    r = stages.read(_now(stages))
    assert r.mode == StageMode.HOLDING and r.closing_m == pytest.approx(held)
    assert "/1 1 stop" in emu.received and "/2 1 stop" in emu.received


def test_strain_over_the_limits_refused_before_any_byte(stages, emu):
    sent = len(emu.received)
    for strain in (0.06, -0.01, float("nan")):
        with pytest.raises(LimitError):
            stages.command(StageCommand(target_strain=strain))
    time.sleep(0.05)
    assert len(emu.received) == sent
    r = stages.read(_now(stages))                              # nothing pending: no move
    assert r.mode == StageMode.IDLE and not any("move" in c for c in emu.received)


def test_jam_busy_without_progress_faults_at_the_deadline(stages, emu):
    emu.jam(1, 1, at_steps=2000)                               # bottom stalls at 1 mm, BUSY
    stages.command(StageCommand(target_strain=0.02))
    t0 = time.monotonic()
    r = _read_until(stages, lambda r: r.mode == StageMode.FAULT)
    took = time.monotonic() - t0
    assert r.mode == StageMode.FAULT
    assert 0.2 * 1.5 + 0.2 - 0.05 < took < 2.0                 # eta x 1.5 + 0.2 s, no sooner
    fault = stages.status.fault
    assert "not reached within 0.5 s" in fault and "jammed?" in fault and "\n" not in fault
    assert emu.position(1, 1) == 2000 and "/1 1 stop" in emu.received
    with pytest.raises(LimitError, match="FAULT"):
        stages.command(StageCommand(target_strain=0.01))
    emu.jam(1, 1, None)
    stages.command(StageCommand(reset=True))
    r = stages.read(_now(stages))
    assert r.mode == StageMode.IDLE and stages.status.fault == ""
    stages.command(StageCommand(target_strain=0.0))            # back out after the reset
    r = _read_until(stages, lambda r: r.mode != StageMode.MOVING)
    assert r.mode == StageMode.HOLDING and r.closing_m == pytest.approx(0.0)


def test_stall_flag_faults_at_once(stages, emu):
    emu.jam(2, 1, at_steps=1500, flag="FS")
    stages.command(StageCommand(target_strain=0.05))           # would take 0.5 s
    t0 = time.monotonic()
    r = _read_until(stages, lambda r: r.mode == StageMode.FAULT)
    assert r.mode == StageMode.FAULT and time.monotonic() - t0 < 0.9   # deadline: 0.95 s
    assert stages.status.fault.startswith("top stage (device 2 axis 1) reports fault FS "
                                          "(stalled and stopped)")


def test_silent_controller_faults_within_a_bounded_time(stages, emu):
    stages.command(StageCommand(target_strain=0.05))
    stages.read(_now(stages))
    emu.silent = True
    t0 = time.monotonic()
    r = stages.read(_now(stages))
    took = time.monotonic() - t0
    assert r.mode == StageMode.FAULT and took < 3 * CFG.reply_timeout_s + 0.7
    assert stages.status.fault == (f"no reply from the stage controller on {emu.port} to "
                                   "'/1 1 get pos' within 0.1 s (power, cable, device number?)")
    t0 = time.monotonic()
    stages.command(StageCommand(reset=True))                   # still silent: still FAULT
    r = stages.read(_now(stages))
    assert r.mode == StageMode.FAULT and time.monotonic() - t0 < 3 * CFG.reply_timeout_s + 0.7
    assert "no reply" in stages.status.fault


def test_a_controller_that_never_answers_is_refused_on_open(emu):
    emu.silent = True
    t0 = time.monotonic()
    with pytest.raises(StageControllerError, match=r"no reply .* to '/1 1 set maxspeed \d+'"):
        ZaberStages(emu.port, CFG)
    assert time.monotonic() - t0 < 1.0
    with pytest.raises(StageControllerError, match="cannot open the stage controller's port"):
        ZaberStages("/nonexistent/ttyUSB9", CFG)


def test_config_keeps_the_strain_rate_limit():
    with pytest.raises(ValueError, match="strain rate"):
        ZaberConfig(sample_height_m=0.2, max_strain_rate_per_s=0.01, closing_speed_m_s=0.01)
