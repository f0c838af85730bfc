"""Shaker simulator: limits, second-order response, determinism."""

import math

import numpy as np
import pytest

from devices.limits import LimitError
from devices.shaker.waveform import Program, WaveformRequest, make_waveform
from hardware_sim import shaker as sh


def test_pulse_waveform_closed_form():
    wf = make_waveform(sh.ShakerConfig(), WaveformRequest("pulse", 0.0075, 30.0))
    assert wf.duration_s == pytest.approx(1 / 30)
    t = np.array([-0.01, 0.0, 1 / 60, 1 / 30, 0.05])
    np.testing.assert_allclose(wf.displacement(t), [0, 0, 0.0075, 0, 0], atol=1e-15)
    # velocity peak (A/2) 2 pi f = pi A f at a quarter period
    assert wf.velocity(1 / 120) == pytest.approx(math.pi * 0.0075 * 30)


@pytest.mark.parametrize("req, words", [
    (WaveformRequest("pulse", 0.02, 30.0), "amplitude"),
    (WaveformRequest("pulse", -0.001, 30.0), "amplitude"),
    (WaveformRequest("pulse", 0.005, 500.0), "frequency"),
    (WaveformRequest("burst", 0.01, 60.0, cycles=2), "velocity"),
    (WaveformRequest("square", 0.005, 30.0), "unknown waveform"),
    (WaveformRequest("pulse", float("nan"), 30.0), "finite"),
    (WaveformRequest("samples", samples_m=(0.0, 0.05), sample_rate_hz=1000.0), "amplitude"),
])
def test_limits_refuse_with_reason(req, words):
    with pytest.raises(LimitError, match=words):
        make_waveform(sh.ShakerConfig(), req)


def test_second_order_step_response_settles_with_expected_overshoot():
    cfg = sh.ShakerConfig(natural_frequency_hz=100.0, damping_ratio=0.5, noise_std_m=0.0,
                          noise_std_m_s=0.0)
    rng = np.random.default_rng(0)
    st = sh.init(cfg, rng)
    xs = []
    for _ in range(400):
        st, r = sh.step(cfg, st, 1e-3, 1e-4, rng)
        xs.append(r.x_m)
    xs = np.array(xs)
    overshoot = xs.max() / 1e-3 - 1
    zeta = 0.5
    assert overshoot == pytest.approx(math.exp(-zeta * math.pi / math.sqrt(1 - zeta**2)), rel=0.02)
    assert xs[-1] == pytest.approx(1e-3, rel=1e-3)


def test_run_tracks_pulse_and_is_deterministic():
    cfg = sh.ShakerConfig()
    wf = make_waveform(cfg, WaveformRequest("pulse", 0.0075, 30.0))
    t = np.arange(1, 101) * 1e-3
    _, a = sh.run(cfg, wf, t, 0.01, np.random.default_rng(3))
    _, b = sh.run(cfg, wf, t, 0.01, np.random.default_rng(3))
    np.testing.assert_array_equal(a, b)
    # a 250 Hz actuator lags a 30 Hz pulse by ~2 zeta/wn ~ 0.9 ms: peak within 2 ms of 26.7 ms
    assert a[np.argmax(a[:, 1]), 0] == pytest.approx(0.01 + 1 / 60, abs=2e-3)
    assert a[:, 1].max() == pytest.approx(0.0075, rel=0.03)
    assert abs(a[-1, 1]) < 1e-4  # back at rest after the pulse


def test_advance_is_independent_of_call_rate():
    cfg = sh.ShakerConfig(noise_std_m=0.0, noise_std_m_s=0.0)
    prog = Program(make_waveform(cfg, WaveformRequest("pulse", 0.005, 40.0)), 0.002)
    rng = np.random.default_rng(0)
    fine, coarse = sh.init(cfg, rng), sh.init(cfg, rng)
    for k in range(1, 17):
        fine, _ = sh.advance(cfg, fine, prog, k * 1e-3, rng)
        if k % 4 == 0:
            coarse, _ = sh.advance(cfg, coarse, prog, k * 1e-3, rng)
    assert coarse.x == pytest.approx(fine.x, abs=1e-7)  # far below the 2 um sensor noise
    assert fine.x > 0.004  # 16 ms: near the pulse peak at 2 ms + 12.5 ms (+ lag)
    assert prog.end_s == pytest.approx(0.027)


def test_the_simulated_shaker_is_a_shaker_drive_behind_the_port():
    """The port's contract on the simulator: requests checked by `prepare` before the drive is
    called; an accepted pulse played from its start time; `stop` drops it (back to rest)."""
    from devices.shaker.port import ShakerDrive, prepare

    cfg = sh.ShakerConfig(noise_std_m=0.0, noise_std_m_s=0.0)
    drive = sh.SimulatedShaker(cfg, np.random.default_rng(0))
    assert isinstance(drive, ShakerDrive)
    with pytest.raises(LimitError, match="delay"):
        prepare(drive.limits, WaveformRequest("pulse", 0.005, 30.0), delay_s=-1.0)
    with pytest.raises(LimitError, match="amplitude"):
        prepare(drive.limits, WaveformRequest("pulse", 0.05, 30.0))
    drive.start(1.0)
    wf = prepare(drive.limits, WaveformRequest("pulse", 0.005, 30.0))
    drive.play(wf, 1.01)
    x = np.array([drive.read(1.0 + k * 1e-3).x_m for k in range(1, 80)])
    assert np.all(np.abs(x[:9]) < 1e-12)  # nothing before the start
    assert 0.9 * 0.005 < x.max() < 1.1 * 0.005  # the 250 Hz actuator follows a 30 Hz pulse
    burst = prepare(drive.limits, WaveformRequest("burst", 0.005, 30.0, cycles=30))  # 1 s
    drive.play(burst, drive.time_s)
    assert abs(drive.read(drive.time_s + 0.1083).x_m) > 0.002  # playing (near a crest)
    drive.stop()
    assert abs(drive.read(drive.time_s + 0.2).x_m) < 1e-6  # at rest long before the burst ends
