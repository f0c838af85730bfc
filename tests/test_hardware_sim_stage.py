"""Linear stage simulator: limits, rate-limited motion, holding, stop, jam fault."""

import numpy as np
import pytest

from hardware_sim import stage as sg
from devices.limits import LimitError
from devices.stage.port import StageCommand, StageMode


def _run(cfg, st, cmd, seconds, dt=1e-3, rng=None):
    rng = rng or np.random.default_rng(0)
    st, r = sg.step(cfg, st, cmd, dt, rng)
    for _ in range(int(round(seconds / dt)) - 1):
        st, r = sg.step(cfg, st, StageCommand(), dt, rng)
    return st, r


def test_moves_at_rate_then_holds():
    cfg = sg.StageConfig(noise_std_m=0.0)
    st = sg.init(cfg, np.random.default_rng(0))
    st, r = _run(cfg, st, StageCommand(target_strain=0.02), 0.04)
    assert st.mode == StageMode.MOVING
    assert st.closing_m == pytest.approx(0.04 * cfg.closing_speed_m_s, rel=1e-9)
    st, r = _run(cfg, st, StageCommand(), 0.06)
    assert st.mode == StageMode.HOLDING
    assert r.closing_m == pytest.approx(0.02 * cfg.sample_height_m)
    assert sg.eta_s(cfg, sg.init(cfg, None), 0.02) == pytest.approx(0.08)


@pytest.mark.parametrize("strain", [0.2, -0.01, float("inf")])
def test_refuses_out_of_limit_strain(strain):
    cfg = sg.StageConfig()
    with pytest.raises(LimitError, match="strain"):
        sg.step(cfg, sg.init(cfg, None), StageCommand(target_strain=strain), 1e-3,
                np.random.default_rng(0))


def test_config_refuses_too_fast_closing():
    with pytest.raises(ValueError, match="strain rate"):
        sg.StageConfig(closing_speed_m_s=1.0)


def test_stop_holds_in_place():
    cfg = sg.StageConfig(noise_std_m=0.0)
    st, _ = _run(cfg, sg.init(cfg, None), StageCommand(target_strain=0.05), 0.05)
    st, _ = _run(cfg, st, StageCommand(stop=True), 0.05)
    assert st.mode == StageMode.HOLDING
    assert st.closing_m == pytest.approx(0.05 * cfg.closing_speed_m_s)


def test_jam_faults_and_needs_reset():
    cfg = sg.StageConfig(noise_std_m=0.0, jam_closing_m=0.002)
    st, _ = _run(cfg, sg.init(cfg, None), StageCommand(target_strain=0.02), 0.08)
    assert st.mode == StageMode.FAULT and "following error" in st.fault
    assert st.closing_m == pytest.approx(0.002)
    with pytest.raises(LimitError, match="FAULT"):
        sg.step(cfg, st, StageCommand(target_strain=0.0), 1e-3, np.random.default_rng(0))
    st, _ = sg.step(cfg, st, StageCommand(reset=True), 1e-3, np.random.default_rng(0))
    assert st.mode == StageMode.IDLE


def test_the_simulated_stages_are_a_stage_pair_behind_the_port():
    """The port's contract on the simulator: a command acts at the next reading, once; the
    status follows; the limits are the configuration's."""
    from devices.stage.port import StagePair, check_strain

    cfg = sg.StageConfig(noise_std_m=0.0)
    stages = sg.SimulatedStages(cfg, np.random.default_rng(0))
    assert isinstance(stages, StagePair) and stages.limits.max_strain == cfg.max_strain
    with pytest.raises(LimitError, match="outside the limits"):
        check_strain(stages.limits, 0.5)
    stages.start(2.0)
    stages.command(StageCommand(target_strain=0.02))
    assert stages.eta_s(0.02) == pytest.approx(0.08)
    for k in range(1, 121):  # 0.12 s at 1 kHz: there after 0.08 s
        r = stages.read(2.0 + k * 1e-3)
    assert stages.status.mode == StageMode.HOLDING and stages.time_s == pytest.approx(2.12)
    assert r.closing_m == pytest.approx(0.02 * cfg.sample_height_m, abs=1e-12)
    stages.command(StageCommand(target_strain=0.0))
    stages.read(2.121)
    stages.command(StageCommand(stop=True))  # stops on the way back, and holds there
    stages.read(2.122)
    held = stages.status.closing_m
    for k in range(3, 50):
        stages.read(2.12 + k * 1e-3)
    assert stages.status.mode == StageMode.HOLDING and stages.status.closing_m == held
    assert 0.0 < held < 0.02 * cfg.sample_height_m
