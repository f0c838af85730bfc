"""Fields and errors of a measured trajectory against a simulated one (numpy, SI).

Both trajectories are sampled at the same times. Velocities of both come from their positions
by the same differentiating filter (`frame_rates`), so the differencing of camera data biases
neither side. Units
lost in any frame are excluded from every field and error, and counted.
"""

from dataclasses import dataclass

import numpy as np

from metarig.trajectory import Trajectory

ONSET_LEVEL = 0.02  # fraction of the input's peak that marks its rise


@dataclass(frozen=True)
class Comparison:
    """Measured (exp) against simulated (sim) motion on the window after the pulse onset.

    Attributes:
        t: [n_t] time since the pulse onset, s.
        speed_exp, speed_sim: [n_t, n_units] translational speed, m/s (NaN: excluded unit).
        ke_exp, ke_sim: [n_t, n_units] kinetic energy (translation + rotation), J.
        target_ke_exp, target_ke_sim: [n_t] kinetic energy of the target units, J.
        row_peak_ke_exp, row_peak_ke_sim: [n_row] peak kinetic energy along the row, J.
        displacement_error_m: [n_t, n_units] |(u, v) measured - simulated|, m.
        velocity_error_t: [n_t] RMS velocity difference over the used units at each sample,
            over the RMS simulated velocity of the whole window (its mean square is NRMSE^2).
        used: [n_units] units in the comparison (never lost).
        metrics: the summary numbers (see `compare`).
    """

    t: np.ndarray
    speed_exp: np.ndarray
    speed_sim: np.ndarray
    ke_exp: np.ndarray
    ke_sim: np.ndarray
    target_ke_exp: np.ndarray
    target_ke_sim: np.ndarray
    row_peak_ke_exp: np.ndarray
    row_peak_ke_sim: np.ndarray
    displacement_error_m: np.ndarray
    velocity_error_t: np.ndarray
    used: np.ndarray
    metrics: dict


def pulse_onset(t: np.ndarray, u: np.ndarray) -> float:
    """Onset time (s) of a pulse in a signal u [n] (m) sampled at t [n] (s).

    The rise is found at 2 % and 8 % of the peak departure from the initial level; a smooth
    (quadratic) start is extrapolated back from those two crossings, never before the record.

    Raises:
        ValueError: no pulse stands out of the signal's initial noise.
    """
    t, u = np.asarray(t, np.float64), np.asarray(u, np.float64)
    ok = np.isfinite(u)
    t, u = t[ok], u[ok]
    if t.size < 4:
        raise ValueError("too few input samples to find the pulse onset")
    base = np.median(u[: max(3, t.size // 20)])
    dev = np.abs(u - base)
    peak = dev.max()
    noise = np.std(u[: max(3, t.size // 20)])
    if peak <= 0 or peak < 10 * noise:
        raise ValueError("no pulse found in the measured input (flat or noise only)")
    k1 = int(np.argmax(dev > ONSET_LEVEL * peak))
    k2 = int(np.argmax(dev > 4 * ONSET_LEVEL * peak))

    def crossing(k, level):
        if k == 0:
            return t[0]
        a, b = dev[k - 1], dev[k]
        return t[k - 1] + (level - a) / (b - a) * (t[k] - t[k - 1])

    t1, t2 = crossing(k1, ONSET_LEVEL * peak), crossing(k2, 4 * ONSET_LEVEL * peak)
    return float(np.clip(2 * t1 - t2, t[0], t1))


RATE_WINDOW = 5  # samples of the Savitzky-Golay derivative (quadratic fit)


def frame_rates(t: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Rates [n_t, ...] of positions q [n_t, ...] sampled at times t [n_t]: the derivative of a
    local quadratic fit over `RATE_WINDOW` samples (Savitzky-Golay) on a uniform time axis,
    which has sqrt(5) less noise than a central difference and follows a 30-300 Hz motion
    sampled at 1 kHz within a percent; central differences on a non-uniform axis. NaN spreads
    from a lost sample to its neighbours."""
    from scipy.signal import savgol_filter

    t, q = np.asarray(t, np.float64), np.asarray(q, np.float64)
    out = np.gradient(q, t, axis=0) if t.size >= 2 else np.full_like(q, np.nan)
    dt = np.diff(t)
    if t.size >= RATE_WINDOW and np.allclose(dt, dt[0], rtol=1e-6, atol=0):
        flat, rates = q.reshape(t.size, -1), out.reshape(t.size, -1)
        ok = np.all(np.isfinite(flat), axis=0)  # series with a lost sample keep NaN there
        rates[:, ok] = savgol_filter(flat[:, ok], RATE_WINDOW, 2, deriv=1, delta=float(dt[0]),
                                     axis=0, mode="interp")
    return out


# Share of a tracked pose's stated variance (`Trajectory.sigma`) that reaches the rates as
# noise white from frame to frame; the rest is common to every frame of a unit (the reference
# image's noise) and does not reach velocities. Calibrated on the rig's footage, where the
# comparison uses it: the share with which the stated rate noise equals, in mean square, the
# error of the tracked rates against the true ones is 0.64 on the default `metarig rig` at 2 %
# and 5 % (8-frame reference; benchmarks/bench_precompressed.py, `velocity_nrmse_tracked_vs_truth`
# against `velocity_noise_nrmse_stated`, run at 0.9) and about 0.69 on
# recordings/precompression-12x8 (single-frame reference; tests/test_compare_cli.py). It is less
# than the pose errors' white share (with the 8-frame reference 0.86-0.94 on the optimised
# design and 0.88-0.89 on the periodic one of benchmarks/bench_dic_design.py, `white_share`;
# 0.35-0.65 with one frame), and on that benchmark's blurred 0.4 mm/px footage the rates' error
# is larger instead (1.7-2.7 times a share of 1, `velocity_error_share`; 73-81 % within 2 sigma
# at 0.9): not white noise, and not explained yet. The stated noise is an estimate for the
# comparison's NRMSE, not a per-sample bound.
FRAME_NOISE_SHARE = 0.65


def rate_noise_var(t: np.ndarray, var: np.ndarray) -> np.ndarray:
    """Variance [n_t, ...] of `frame_rates(t, q)` caused by independent noise of variance
    var [n_t, ...] in each sample of q (the filter is linear: its weights squared times var;
    NaN where a sample's variance is unknown)."""
    t = np.asarray(t, np.float64)
    weights = frame_rates(t, np.eye(t.size))  # [i, j]: rate at i per unit of sample j
    v = np.asarray(var, np.float64).reshape(t.size, -1)
    return (weights**2 @ v).reshape(np.shape(var))


def kinetic_energy(qdot: np.ndarray, mass: np.ndarray, inertia: np.ndarray) -> np.ndarray:
    """[..., n] kinetic energy (J) of rates qdot [..., n, 3] (m/s, m/s, rad/s) for masses [n]
    (kg) and rotary inertias [n] (kg m^2) about the area centroids."""
    return 0.5 * (mass * (qdot[..., 0] ** 2 + qdot[..., 1] ** 2) + inertia * qdot[..., 2] ** 2)


def _velocity_noise(t: np.ndarray, sigma: np.ndarray | None, used: np.ndarray,
                    keep: np.ndarray) -> float:
    """Mean squared translational velocity error (m^2/s^2, both components) that the stated
    pose errors cause over the used units and kept samples; NaN where any is unknown."""
    if sigma is None:
        return float("nan")
    var = FRAME_NOISE_SHARE * np.asarray(sigma, np.float64)[:, used, :2] ** 2
    if not np.all(np.isfinite(var)):
        return float("nan")
    return float(np.mean(np.sum(rate_noise_var(t, var)[keep], axis=-1)))


def compare(measured: Trajectory, simulated: Trajectory, mass: np.ndarray, inertia: np.ndarray,
            target: np.ndarray, row: np.ndarray, onset_s: float) -> Comparison:
    """Compare two trajectories on the same times from the onset on.

    Args:
        measured: tracked motion (q relative to the first frame; `lost` marks untracked units).
        simulated: the engine's motion on the measured input, at the same times, q relative to
            the same first frame.
        mass, inertia: [n_units] kg and kg m^2.
        target: ids of the target units; row: ids of the units along the spec's row, in order.
        onset_s: pulse onset on the trajectories' time axis, s.

    Returns:
        `Comparison` whose metrics are: `velocity_nrmse` (RMS of the velocity difference over
        the RMS simulated velocity, all used units and samples), `energy_map_correlation`
        (Pearson correlation of the time-averaged kinetic-energy maps), `target_peak_ke_rel_err`
        (signed relative error of the measured peak target energy), `max_displacement_error_m`,
        `lost_units`, `units_compared`, `onset_s` and the two peak target energies (J).
        Where every used pose has a stated standard error (`measured.sigma`), also
        `velocity_noise_nrmse`, what the tracking noise alone adds to a perfect model's NRMSE
        (the frame's own share of the variance, `FRAME_NOISE_SHARE`, through the same
        differentiating filter), and `velocity_nrmse_beyond_noise` = sqrt(NRMSE^2 - that^2),
        the part of the error the tracking noise does not explain (the model's).

    Raises:
        ValueError: different time axes or unit counts, too few samples, or nothing to compare.
    """
    if measured.n_units != simulated.n_units:
        raise ValueError(f"the recording has {measured.n_units} units but the simulation "
                         f"{simulated.n_units}: the design does not match the recording")
    if measured.n_t != simulated.n_t or not np.allclose(measured.t, simulated.t, atol=1e-9):
        raise ValueError("measured and simulated trajectories must share their time axis")
    keep = measured.t >= onset_s - 1e-9
    if keep.sum() < 3:
        raise ValueError(f"only {int(keep.sum())} frames after the pulse onset; need 3 or more")
    used = measured.valid.all(axis=0)
    lost_units = int((~used).sum())
    if not used.any():
        raise ValueError("every unit was lost in some frame: nothing to compare")
    t = measured.t
    qd_exp = frame_rates(t, measured.q)[keep]
    qd_sim = frame_rates(t, simulated.q)[keep]
    nan_out = np.where(used, 1.0, np.nan)
    ke_exp = kinetic_energy(qd_exp, mass, inertia) * nan_out
    ke_sim = kinetic_energy(qd_sim, mass, inertia) * nan_out
    speed_exp = np.hypot(qd_exp[..., 0], qd_exp[..., 1]) * nan_out
    speed_sim = np.hypot(qd_sim[..., 0], qd_sim[..., 1]) * nan_out
    dv = qd_exp[:, used, :2] - qd_sim[:, used, :2]
    v_rms_sim = np.sqrt(np.mean(np.sum(qd_sim[:, used, :2] ** 2, axis=-1)))
    nrmse = float(np.sqrt(np.mean(np.sum(dv**2, axis=-1))) / v_rms_sim) if v_rms_sim > 0 \
        else float("nan")
    noise = _velocity_noise(t, measured.sigma, used, keep)
    noise_nrmse = float(np.sqrt(noise) / v_rms_sim) if v_rms_sim > 0 else float("nan")
    map_e, map_s = ke_exp[:, used].mean(axis=0), ke_sim[:, used].mean(axis=0)
    corr = float(np.corrcoef(map_e, map_s)[0, 1]) if used.sum() > 1 else float("nan")
    tgt = np.asarray(target)[used[np.asarray(target)]]
    target_exp = ke_exp[:, tgt].sum(axis=1)
    target_sim = ke_sim[:, tgt].sum(axis=1)
    peak_e, peak_s = float(target_exp.max(initial=0.0)), float(target_sim.max(initial=0.0))
    disp = np.hypot(*(measured.q[keep][..., :2] - simulated.q[keep][..., :2]).transpose(2, 0, 1))
    disp = disp * nan_out
    metrics = {
        "velocity_nrmse": nrmse,
        "energy_map_correlation": corr,
        "target_peak_ke_rel_err": (peak_e - peak_s) / peak_s if peak_s > 0 else float("nan"),
        "max_displacement_error_m": float(np.nanmax(disp)),
        "lost_units": lost_units,
        "units_compared": int(used.sum()),
        "target_units_compared": int(tgt.size),
        "onset_s": float(onset_s),
        "target_peak_ke_exp_J": peak_e,
        "target_peak_ke_sim_J": peak_s,
    }
    if np.isfinite(noise_nrmse):
        metrics["velocity_noise_nrmse"] = noise_nrmse
        metrics["velocity_nrmse_beyond_noise"] = float(np.sqrt(max(nrmse**2 - noise_nrmse**2,
                                                                   0.0)))
    row = np.asarray(row)
    return Comparison(
        t=t[keep] - onset_s, speed_exp=speed_exp, speed_sim=speed_sim, ke_exp=ke_exp,
        ke_sim=ke_sim, target_ke_exp=target_exp, target_ke_sim=target_sim,
        row_peak_ke_exp=ke_exp[:, row].max(axis=0), row_peak_ke_sim=ke_sim[:, row].max(axis=0),
        displacement_error_m=disp,
        velocity_error_t=np.sqrt(np.mean(np.sum(dv**2, axis=-1), axis=1)) / v_rms_sim
        if v_rms_sim > 0 else np.full(int(keep.sum()), np.nan),
        used=used, metrics=metrics)
