"""Drive compensation (`devices.shaker.compensation`) on the simulated shaker, whose actuator
has its own dynamics: the measured pulse brought within the stated tolerance of the request,
every drive within the caps and the limits, and a drive the limits refuse never played."""

import numpy as np
import pytest

from devices.shaker.compensation import CompensationConfig, compensate, window
from devices.shaker.waveform import WaveformRequest, make_waveform
from hardware_sim.shaker import ShakerConfig, SimulatedShaker

RATE_HZ = 2000.0


def _measure(cfg: ShakerConfig, played: list):
    """Play a drive on a simulated shaker from rest and read its sensor at the drive's times."""
    def measure(drive):
        played.append(drive)
        shaker = SimulatedShaker(cfg, np.random.default_rng(len(played)))
        shaker.start(0.0)
        shaker.play(drive, 0.0)
        return np.array([shaker.read(t).x_m for t in np.arange(drive.samples_m.size) / RATE_HZ])
    return measure


def test_a_resonant_shaker_is_brought_to_the_requested_pulse():
    # an actuator at 80 Hz with 0.3 damping overshoots the paper's pulse as the lab's did
    # (7.5 mm requested, 7.98 mm measured: the published 7.9-8.7 mm)
    cfg = ShakerConfig(natural_frequency_hz=80.0, damping_ratio=0.3)
    request = make_waveform(cfg, WaveformRequest("pulse", 0.0075, 30.0))
    played = []
    c = CompensationConfig()
    result = compensate(request, cfg, _measure(cfg, played), RATE_HZ, c)
    peak, rms = result.peak_errors, result.rms_errors
    assert 0.05 < peak[0] < 0.08 and rms[0] > 0.07  # uncompensated
    assert result.converged and result.stopped == "within the tolerances", result
    assert abs(peak[-1]) <= c.peak_tolerance and rms[-1] <= c.rms_tolerance
    # each try closer: measured 8.9 %, 1.8 %, 0.4 % RMS
    assert list(rms) == sorted(rms, reverse=True) and len(rms) <= 4
    assert result.drive is played[-1] and len(played) == len(rms)
    # every drive played started at rest, ended at rest and kept within the caps
    drives = [d.samples_m for d in played]
    assert all(d[0] == 0.0 and abs(d[-1]) < 1e-9 for d in drives)
    assert all(np.abs(d).max() <= c.max_drive * 0.0075 + 1e-12 for d in drives)
    assert all(np.abs(b - a).max() <= c.max_step * 0.0075 + 1e-12
               for a, b in zip(drives, drives[1:]))
    assert drives[0].size == window(request, RATE_HZ, c.tail_periods).size


def test_the_default_shaker_lag_is_compensated_too():
    cfg = ShakerConfig()
    request = make_waveform(cfg, WaveformRequest("pulse", 0.0075, 30.0))
    result = compensate(request, cfg, _measure(cfg, []), RATE_HZ)
    assert result.rms_errors[0] > 0.04  # 250 Hz actuator: the pulse lags
    assert result.converged and result.rms_errors[-1] <= 0.01


def test_a_drive_beyond_the_limits_is_never_played():
    # a sluggish actuator needs more drive than the request; the limits allow 8 mm only
    cfg = ShakerConfig(natural_frequency_hz=40.0, damping_ratio=1.5, max_amplitude_m=0.008)
    request = make_waveform(cfg, WaveformRequest("pulse", 0.0075, 30.0))
    played = []
    result = compensate(request, cfg, _measure(cfg, played), RATE_HZ)
    assert not result.converged
    assert result.stopped.startswith("the next drive is outside the limits: amplitude ")
    assert all(np.abs(d.samples_m).max() <= 0.008 for d in played)
    assert result.drive is played[-1]


def test_only_pulses_and_bursts_are_compensated():
    cfg = ShakerConfig()
    samples = make_waveform(cfg, WaveformRequest("samples", samples_m=(0.0, 0.001, 0.0),
                                                 sample_rate_hz=100.0))
    with pytest.raises(ValueError, match="compensate a pulse or a burst"):
        compensate(samples, cfg, lambda d: np.zeros(3), RATE_HZ)
