"""Comparison fields and errors on synthetic trajectories with known answers (numpy only)."""

import numpy as np
import pytest

from comparison.metrics import FRAME_NOISE_SHARE, compare, kinetic_energy, pulse_onset
from metarig.trajectory import Trajectory


def _wave(nt=120, n=12, fps=1000.0, scale=1.0, onset=0.01):
    t = np.arange(nt) / fps
    x = np.arange(n) * 0.015
    tau = np.clip(t[:, None] - onset - x[None, :] / 5.0, 0.0, None)  # a travelling pulse
    q = np.zeros((nt, n, 3))
    q[..., 0] = scale * 1e-3 * np.sin(2 * np.pi * 30 * tau) * (tau > 0)
    q[..., 2] = scale * 1e-2 * np.sin(2 * np.pi * 30 * tau) * (tau > 0)
    return Trajectory.from_positions(t, q)


MASS, INERTIA = np.full(12, 2e-3), np.full(12, 5e-8)
TARGET, ROW = np.array([8, 9]), np.arange(12)


def test_a_trajectory_compared_with_itself_has_no_error():
    a = _wave()
    c = compare(a, a, MASS, INERTIA, TARGET, ROW, onset_s=0.01)
    m = c.metrics
    assert m["velocity_nrmse"] == 0.0 and m["max_displacement_error_m"] == 0.0
    assert m["energy_map_correlation"] == pytest.approx(1.0)
    assert m["target_peak_ke_rel_err"] == 0.0 and m["lost_units"] == 0
    assert c.t[0] == pytest.approx(0.0) and c.row_peak_ke_exp.shape == (12,)


def test_known_scaling_gives_known_errors():
    sim, exp = _wave(), _wave(scale=1.2)
    m = compare(exp, sim, MASS, INERTIA, TARGET, ROW, onset_s=0.01).metrics
    assert m["velocity_nrmse"] == pytest.approx(0.2, rel=1e-9)
    c = compare(exp, sim, MASS, INERTIA, TARGET, ROW, onset_s=0.01)
    assert np.sqrt(np.mean(c.velocity_error_t**2)) == pytest.approx(0.2, rel=1e-9)
    assert m["target_peak_ke_rel_err"] == pytest.approx(1.2**2 - 1, rel=1e-9)  # energy ~ v^2
    assert m["energy_map_correlation"] == pytest.approx(1.0)  # same shape, other scale
    assert m["max_displacement_error_m"] == pytest.approx(0.2e-3, rel=1e-3)


def test_lost_units_are_excluded_and_counted_never_filled_in():
    sim = _wave()
    lost = np.zeros((sim.n_t, 12), bool)
    lost[50, 9] = True
    q = sim.q.copy()
    q[lost] = 1.0  # garbage where lost: must not leak into any number
    exp = Trajectory.from_positions(sim.t, q, lost=lost)
    c = compare(exp, sim, MASS, INERTIA, TARGET, ROW, onset_s=0.01)
    assert c.metrics["lost_units"] == 1 and c.metrics["units_compared"] == 11
    assert c.metrics["target_units_compared"] == 1
    assert c.metrics["velocity_nrmse"] == 0.0 and not c.used[9]
    assert np.isnan(c.ke_exp[:, 9]).all() and np.isnan(c.row_peak_ke_exp[9])


def test_kinetic_energy_of_translation_and_rotation():
    qdot = np.array([[[3.0, 4.0, 2.0]]])
    assert kinetic_energy(qdot, np.array([2.0]), np.array([0.5]))[0, 0] == pytest.approx(26.0)


def test_mismatches_are_refused_in_one_line():
    a = _wave()
    with pytest.raises(ValueError, match="design does not match the recording"):
        compare(a, _wave(n=10), MASS, INERTIA, TARGET, ROW, 0.01)
    with pytest.raises(ValueError, match="frames after the pulse onset"):
        compare(a, a, MASS, INERTIA, TARGET, ROW, onset_s=1.0)
    every = Trajectory.from_positions(a.t, a.q, lost=np.ones((a.n_t, 12), bool))
    with pytest.raises(ValueError, match="every unit was lost"):
        compare(every, a, MASS, INERTIA, TARGET, ROW, 0.01)


@pytest.mark.parametrize("onset", [0.005, 0.0123])
def test_pulse_onset_of_a_noisy_one_minus_cosine_pulse(onset):
    rng = np.random.default_rng(3)
    t = np.arange(80) / 1000.0
    tau = np.clip(t - onset, 0, 1 / 30)
    u = 3.75e-3 * (1 - np.cos(2 * np.pi * 30 * tau)) + rng.normal(scale=2e-6, size=t.size)
    assert pulse_onset(t, u) == pytest.approx(onset, abs=0.6e-3)
    with pytest.raises(ValueError, match="no pulse"):
        pulse_onset(t, rng.normal(scale=2e-6, size=t.size))


def _noisy(traj, sigma, seed):
    """traj with tracking-like errors of stated standard error `sigma` (m, rad): a share
    `FRAME_NOISE_SHARE` of the variance white from frame to frame, the rest a per-unit constant
    (the reference image's noise)."""
    rng = np.random.default_rng(seed)
    n_t, n = traj.q.shape[:2]
    s, share = np.asarray(sigma), FRAME_NOISE_SHARE
    q = traj.q + rng.normal(0.0, 1.0, (1, n, 3)) * s * np.sqrt(1 - share) \
        + rng.normal(0.0, 1.0, (n_t, n, 3)) * s * np.sqrt(share)
    return Trajectory.from_positions(traj.t, q, sigma=np.broadcast_to(sigma, q.shape).copy())


@pytest.mark.parametrize("scale", [1.0, 1.1])
def test_the_tracking_noise_part_of_the_velocity_error_is_told_apart(scale):
    """The stated pose errors predict what noise adds to the NRMSE; what is left is the model's
    error (a perfect model: about 0; a 10 % faster measurement: 10 %)."""
    sim = _wave(nt=400, n=12)
    sigma = (3e-5, 3e-5, 2e-3)
    exp = _noisy(_wave(nt=400, n=12, scale=scale), sigma, seed=3)
    m = compare(exp, sim, MASS, INERTIA, TARGET, ROW, onset_s=0.01).metrics
    clean = compare(_wave(nt=400, n=12, scale=scale), sim, MASS, INERTIA, TARGET, ROW,
                    onset_s=0.01).metrics["velocity_nrmse"]
    assert m["velocity_nrmse"] > clean + 0.01  # the noise matters here
    assert m["velocity_nrmse_beyond_noise"] == pytest.approx(clean, abs=0.01)
    if scale == 1.0:  # the noise alone: its predicted size is what was measured
        assert m["velocity_noise_nrmse"] == pytest.approx(m["velocity_nrmse"], rel=0.1)


def test_no_noise_part_without_stated_pose_errors():
    a = _wave()
    m = compare(a, a, MASS, INERTIA, TARGET, ROW, onset_s=0.01).metrics
    assert "velocity_noise_nrmse" not in m and "velocity_nrmse_beyond_noise" not in m
