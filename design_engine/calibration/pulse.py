"""Pulse experiments: the tracked unit positions of a recorded run against the engine under the
measured input (`fit_pulse`), in windows of growing length (continuation), weighted by the stated
pose errors, with the model error that the tracking noise does not explain (`model_error`).
"""

import math
import time

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

from design_engine.calibration.fit import (CalibrationError, Fit, check_damping_names,
                                           check_fit_names, derived_damping, make_fitted_material,
                                           run_fit, start_damping_ratio)
from design_engine.physics.material import Material
from design_engine.physics.material_file import SI_UNITS

# --- pulse experiments ------------------------------------------------------------------------

PULSE_PARAMS = ("k_stretch", "k_shear", "k_bend", "damping_ratio", "damping_u", "damping_theta")
# What a pulse record pins down: the shear and bending stiffnesses and the damping as one ratio
# (spec 6.3). c_theta alone and k_stretch (the stiff stretch mode is barely excited) move the
# units' positions so little that a separate fit follows the tracker's systematic errors
# (benchmarks/bench_calibrate.py); they stay at the start material's (the hinge tension test
# gives k_stretch) unless --fit names them.
DEFAULT_PULSE_FIT = ("k_shear", "k_bend", "damping_ratio")


def contact_forward_config():
    """Adaptive Dopri8 at the reference tolerances with contact, forward-mode derivatives."""
    from design_engine.solve.simulate import SolverConfig

    return SolverConfig(solver=diffrax.Dopri8(), adjoint=diffrax.ForwardMode())


def pulse_config(scene):
    """Fixed-step Verlet at the automatic step, float64, with contact (for jacfwd): on the
    24x16 focusing design in contact under a 7.5 mm pulse its motion lies within 0.5 um of
    adaptive Dopri8 at the reference tolerances, 8x faster; without contact it is 195 um off.
    Pre-compressed scenes get `contact_forward_config()` (Dopri8)."""
    from design_engine.solve.policy import choose_config
    from design_engine.solve.simulate import SolverConfig

    choice = choose_config(scene)
    if choice.config.use_contact:
        return contact_forward_config()
    # the JAX force (native_force off): jacfwd takes forward-mode derivatives
    return SolverConfig(solver=choice.config.solver, use_contact=True, dtype="float64")


WINDOWS = (0.25, 0.5, 1.0)  # continuation: fractions of the record after the input's onset


def window_frames(frame_t_s, input_t_s, input_u_m, fractions=WINDOWS, min_frames: int = 5):
    """Frame counts of the growing fit windows: each ends `fraction` of the way from the input's
    onset (its first 2 % of the largest excursion) to the last frame. A large-amplitude fit from
    a start 20 % off locks onto the wrong oscillation if it sees the whole record at once (the
    phases have drifted by then); fitting the first swing first avoids that."""
    t = np.asarray(frame_t_s, np.float64)
    u = np.asarray(input_u_m, np.float64) - float(input_u_m[0])
    big = np.abs(u) >= 0.02 * max(float(np.abs(u).max()), 1e-300)
    onset = float(np.asarray(input_t_s)[np.argmax(big)]) if big.any() else float(t[0])
    out = []
    for f in fractions:
        n = int(np.searchsorted(t, onset + f * (t[-1] - onset), side="right"))
        n = t.size if f >= 1.0 else max(n, min_frames)
        if n <= t.size and (not out or n > out[-1]):
            out.append(n)
    return out


DIFFERENCE = np.array([1.0, -4.0, 6.0, -4.0, 1.0])  # 4th difference: white noise x sqrt(70)


def white_noise(r, use) -> float:
    """Standard deviation of the white (frame-to-frame) part of residuals r [n_t, n_units, 2]
    (used where `use` [n_t, n_units]): the median absolute 4th difference in time over the
    frames used with both pairs of neighbours, / (0.6745 sqrt(70)). Tracking noise is white, 70
    sigma^2 in every 4th difference; a model's misfit is smooth at the frame rate (a 60 Hz
    misfit keeps 4e-4 of its power there), and where it is not (a chaotic stretch of a few
    units) the median passes over it."""
    r = np.asarray(r, np.float64)
    n = r.shape[0] - 4
    if n < 1:
        return 0.0
    ok = np.ones((n, r.shape[1]), bool)
    d = np.zeros((n,) + r.shape[1:])
    for k, c in enumerate(DIFFERENCE):
        ok &= use[k:k + n]
        d += c * r[k:k + n]
    d = np.abs(d[ok])
    return float(np.median(d)) / (0.6744897501960817 * math.sqrt(70.0)) if d.size else 0.0


# misfit beyond noise counts as model error only above this many standard deviations of the
# residual sum of squares that noise alone gives (chi^2 with dof degrees of freedom), and two
# windows' values only when they differ by more than this many of their statistical errors
MISFIT_SIGNIFICANCE = 3.0
# ... and only above this fraction of the noise variance: the estimate of the noise is itself
# good to a few per cent (the 4th-difference median on the 8x6 tests' white noise: 3 % low),
# so a smaller misfit is not told apart from it
NOISE_VARIANCE_UNCERTAINTY = 0.1


def model_error(fit: Fit, r, use, data, windows=()) -> dict:
    """The part of a fit's residual that noise does not explain, and what it makes of the
    fitted values: the model error.

    Args:
        fit: the fit (its `extra["J"]`, the residual Jacobian over log values at the optimum).
        r: [n_t, n_units, 2] residual at the optimum (internal units), 0 where not used.
        use: [n_t, n_units] the residuals used.
        data: [n_t, n_units, 2] the fitted data (same units), for the relative size.
        windows: the fits of the shorter windows before `fit` (`fit_pulse`'s continuation).

    Two signs of a model that is wrong, each turned into a standard error of every value:
    - the misfit: the noise sigma is estimated from the residual (`white_noise`); what the
      residual sum of squares holds beyond dof sigma^2, once it exceeds noise by
      `MISFIT_SIGNIFICANCE` standard deviations of chi^2 and `NOISE_VARIANCE_UNCERTAINTY` of
      its variance (reduced chi^2 above 1.1), is the misfit, and the value's model
      error is the change of its log alone that moves the response by the whole misfit,
      |misfit| / |dr/dlog value| (a parameter the response barely depends on gets a large
      one);
    - the windows: a right model gives the same values on the first part of the record as on
      all of it, within their statistical errors; the largest difference between a window's
      value and the whole record's is a model error where the misfit is significant (the
      model is known to be wrong: its values depend on the part of the record fitted), and
      elsewhere where it exceeds `MISFIT_SIGNIFICANCE` of their statistical errors. A chaotic
      record, whose steep Jacobian makes the first measure small and the whole record's
      statistical errors tiny, is caught here.
    The larger of the two is `stderr_model` (SI), which `fit_pulse` adds to the statistical
    error in quadrature. A model that explains the data to their noise gets none. Right for a
    model that is wrong: the fitted constants are then effective ones, which compensate for
    what the model lacks as far as the data let them, and their stated errors must say so.
    """
    n = int(np.sum(use)) * 2
    sigma = white_noise(r, use)
    rss = float(np.sum(np.asarray(r)[use] ** 2))
    dof = max(fit.dof, 1)
    excess = rss - dof * sigma**2
    floor = sigma**2 * max(MISFIT_SIGNIFICANCE * math.sqrt(2.0 * dof),
                           NOISE_VARIANCE_UNCERTAINTY * dof)
    misfit = math.sqrt(excess) if excess > floor else 0.0
    col = np.linalg.norm(np.asarray(fit.extra["J"]), axis=0)
    signal = float(np.sqrt(np.mean(np.asarray(data)[use] ** 2)))
    sd_model, drift = {}, {}
    for i, name in enumerate(fit.names):
        v = float(fit.values[name])
        d = 0.0
        for w in windows:
            diff = abs(math.log(float(w.values[name]) / v))
            stat = math.hypot(float(w.stderr[name]) / float(w.values[name]),
                              float(fit.stderr[name]) / v)
            if misfit > 0 or diff > MISFIT_SIGNIFICANCE * stat:
                d = max(d, diff)
        drift[name] = v * d
        sd_model[name] = max(v * misfit / max(float(col[i]), 1e-300), drift[name])
    scale = 1e-3  # residuals in mm -> m
    return {"noise_m": sigma * scale, "misfit_rms_m": misfit / math.sqrt(max(n, 1)) * scale,
            "relative": misfit / math.sqrt(max(n, 1)) / max(signal, 1e-300),
            "reduced_chi2": rss / dof / sigma**2 if sigma > 0 else None,
            "window_drift": drift, "stderr_model": sd_model}


def pose_weights(sigma, use: np.ndarray) -> np.ndarray | None:
    """Weights [n_t, n_units, 2] of the u, v residuals from the poses' standard errors sigma
    [n_t, n_units, 3] (m): the median over the used poses divided by each one's own; None
    without sigma, or where a used pose has none (or a non-positive one)."""
    if sigma is None:
        return None
    s = np.asarray(sigma, np.float64)[..., :2]
    if s.shape[:2] != use.shape:
        raise CalibrationError(f"pose standard errors {s.shape} do not match the poses")
    used = s[use]
    if used.size == 0 or not np.all(np.isfinite(used)) or np.any(used <= 0):
        return None
    return np.where(use[..., None], np.median(used) / np.where(use[..., None], s, 1.0), 0.0)


def fit_pulse(scene, frame_t_s, tracked_q, valid, input_t_s, input_u_m, stage_t_s=None,
              stage_closing_m=None, fit=DEFAULT_PULSE_FIT, start: Material | None = None,
              config=None, units=None, progress=None, tracked_sigma=None) -> Fit:
    """Fit material constants to a recorded pulse experiment through the engine.

    Args:
        scene: the nominal scene of the recorded design.
        frame_t_s: [n_t] frame times on the rig clock, s (> 0, increasing).
        tracked_q: [n_t, n_units, 3] tracked displacement from the reference configuration
            (m, rad), as the tracker and the rig's ground truth give it; u, v are fitted as
            they are (not relative to the first frame, whose noise would be common to every
            residual of a unit and so make the Gauss-Newton errors too small).
        valid: [n_t, n_units] where the tracked pose holds.
        input_t_s, input_u_m: the measured input (rig clock; smooth it first, as
            `design_engine.solve.run.smooth_input` does), starting at rest.
        stage_t_s, stage_closing_m: the stage closing from rest (or None).
        fit: parameter names; start: start material (default the scene's).
        config: solver configuration (default `pulse_config(scene)`, and
            `contact_forward_config()` if that fixed-step solve is not finite at the start).
        units: optional subset of unit ids whose motion is fitted (default all tracked).
        progress: optional `progress(stage, evaluation, rms_m)` (see `run_fit`).
        tracked_sigma: optional [n_t, n_units, 3] standard errors of `tracked_q` (the
            tracker's, m and rad): each pose's u and v residuals are weighted by the median
            stated error over its own (least squares weighted by 1 / sigma^2, the residual
            still in m of a typical pose), so that poorly tracked units and frames count less;
            `extra["weighted_by_pose_sigma"]` says whether they were (not where any fitted pose
            lacks one).

    Standard errors are two-way cluster-robust over units and time blocks of a tenth of the
    record (`covariance`): tracking errors are correlated along a unit's record, and the
    measured input's errors reach every unit at once; the plain Gauss-Newton errors
    (`extra["stderr_gauss_newton"]`) then claim a precision the data do not hold (on the
    simulated rig's DIC tracks, actual errors 10-20 of them against at most 2 of these).
    The stated `stderr` adds in quadrature the model error (`model_error`: the misfit beyond
    the tracking noise as a change of each value, or the drift of the values between the
    growing windows, whichever is larger; 0 where the model explains the data to their
    noise); `extra["stderr_statistical"]` keeps the cluster-robust part and
    `extra["model_error"]` the figures.
    """
    from design_engine.solve.driver import PolicyFailed, solve_with_policy
    from design_engine.solve.run import measured_loading
    from design_engine.solve.simulate import SimulationError, make_simulator

    names = check_fit_names(list(fit), PULSE_PARAMS, "pulse")
    check_damping_names(names)
    ts_ms = np.asarray(frame_t_s, np.float64) * 1e3
    q = np.asarray(tracked_q, np.float64)
    ok = np.asarray(valid, bool) & np.all(np.isfinite(q), axis=-1)
    if q.ndim != 3 or q.shape[0] != ts_ms.size or q.shape[1] != scene.n_units:
        raise CalibrationError(f"tracked poses {q.shape} do not match {ts_ms.size} frames x "
                               f"{scene.n_units} units")
    if ts_ms.size < 5 or np.any(np.diff(ts_ms) <= 0) or ts_ms[0] <= 0:
        raise CalibrationError("a pulse fit needs 5 or more frames at increasing times > 0")
    use = ok.copy()
    if units is not None:
        mask = np.zeros(scene.n_units, bool)
        mask[np.asarray(units)] = True
        use &= mask[None]
    use[:, np.asarray(scene.input_units)] = False  # the driven units are the input, not data
    if use.sum() < 10:
        raise CalibrationError("fewer than 10 tracked unit poses to fit")
    try:
        loading = measured_loading(scene, input_t_s, input_u_m, stage_t_s, stage_closing_m)
    except ValueError as exc:
        raise CalibrationError(str(exc)) from None
    start = start or scene.material
    start_si = start.to_si()
    start_si["damping_ratio"] = start_damping_ratio(start, scene.lattice)
    material = make_fitted_material(start, names, start_si, scene.lattice)
    data = jnp.asarray(np.where(use[..., None], q[..., :2] * 1e3, 0.0))
    weight = pose_weights(tracked_sigma, use)
    weighted = weight is not None
    weight = jnp.asarray(weight if weighted else np.ones(use.shape + (2,)))
    x = jnp.asarray(scene.design)
    frames = window_frames(ts_ms / 1e3, input_t_s, input_u_m)

    def fit_with(cfg, n, p0=None):
        """The fit on the first n frames."""
        sim = make_simulator(scene.lattice, scene.supports, cfg, ts_ms[:n], model=scene.model)
        tsj = jnp.asarray(ts_ms[:n])
        sel = np.nonzero(np.repeat(use[:n, :, None], 2, axis=-1).reshape(-1))[0]
        unit = (sel // 2) % scene.n_units  # residual order: (frame, unit, u/v)
        block = (sel // 2) // scene.n_units // max(5, n // 10)  # ~10 time blocks

        def simulate(p):
            return sim(x, material(p), loading, tsj)

        def residual(p):
            return ((simulate(p).q[..., :2] - data[:n]) * weight[:n]).reshape(-1)[sel]

        label = "pulse" if n == ts_ms.size else f"pulse, first {n} frames"
        out = run_fit(residual, names, names, start_si, SI_UNITS, "m", scale=1e-3, max_iter=20,
                      p0=p0, progress=progress, clusters=(unit, block), stage=label)
        return out, simulate

    def continuation(cfg):
        """Fit the record in growing windows, each from the last one's result."""
        p, iters, fits = None, 0, []
        for n in frames:
            out, simulate = fit_with(cfg, n, p)
            p, iters = out.extra["p"], iters + out.iterations
            fits.append(out)
        out.iterations = iters
        out.extra["window_fits"] = fits[:-1]
        return out, simulate

    t0 = time.perf_counter()
    if config is not None:
        out, simulate = continuation(config)
    else:  # under the policy driver: a fit that fails (not finite at the start: a fixed step
        # unstable in contact) is redone with Dopri8 in forward mode
        def solve(cfg):
            try:
                return continuation(cfg), None
            except CalibrationError as exc:
                raise SimulationError(str(exc)) from None

        try:
            done = solve_with_policy(scene, pulse_config(scene), solve,
                                     fallback=contact_forward_config())
        except PolicyFailed as exc:
            raise CalibrationError(str(exc)) from None
        (out, simulate), config = done.result, done.config
    # the fitted and the start curves: one compiled program for both (called as it is, each
    # call traced the whole solve op by op, which cost more than the fit's own iterations)
    simulate = jax.jit(simulate)
    sol = simulate(jnp.asarray(out.extra["p"]))
    out.wall_s = time.perf_counter() - t0
    out.extra["windows"] = frames
    out.extra["weighted_by_pose_sigma"] = weighted
    # the model error: the misfit beyond the noise, and the stderr it adds (in quadrature)
    resid = np.where(use[..., None], (np.asarray(sol.q)[..., :2] - np.asarray(data))
                     * np.asarray(weight), 0.0)
    me = model_error(out, resid, use, np.asarray(data) * np.asarray(weight),
                     out.extra.pop("window_fits"))
    out.extra["stderr_statistical"] = dict(out.stderr)
    out.stderr = {n: math.hypot(out.stderr[n], me["stderr_model"][n]) for n in names}
    out.extra["model_error"] = me
    if "damping_ratio" in names:
        out.extra["derived"] = derived_damping(out, material(jnp.asarray(out.extra["p"])))
    out.extra["config"] = f"{type(config.solver).__name__}, contact {config.use_contact}"
    out.extra["min_void_margin"] = float(sol.min_void_margin)
    qs = np.asarray(sol.q) * np.array([1e-3, 1e-3, 1.0])  # SI
    q0 = np.asarray(simulate(jnp.zeros(len(names))).q) * np.array([1e-3, 1e-3, 1.0])
    out.extra["curves"] = {"t_s": ts_ms / 1e3, "data": q, "fitted": qs, "start": q0,
                           "used": use}
    return out

