"""Free oscillation (spec 12.2): two theta0 = 0 units joined by one ligament, one held, the other
released from a rotation; simulated by the engine (`make_oscillation_model`). Fits the damping (a
damping ratio zeta that scales c_u and c_theta as spec 6.3, or the two coefficients) and
`k_bend`; `log_decrement` is the spec's hand method.
"""

import functools
import math
from dataclasses import dataclass

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

from design_engine.calibration.fit import (CalibrationError, Fit, check_damping_names,
                                           check_fit_names, derived_damping, make_fitted_material,
                                           run_fit, start_damping_ratio)
from design_engine.physics.energy import bond_geometry, make_energy
from design_engine.physics.geometry import block_geometry
from design_engine.physics.lattice import Lattice, periodic_design, quads
from design_engine.physics.linalg import implicit_point, spd_solve
from design_engine.physics.loading import CH_ZERO, Loading, Supports
from design_engine.physics.material import Material
from design_engine.physics.material_file import SI_UNITS

# --- free oscillation (spec 12.2) ------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class OscillationSample:
    """Two theta0 = 0 units joined by one ligament; unit 0 held, unit 1 free.

    Attributes:
        lattice, design: the 2 x 1 lattice and its (square-unit) design, mm.
        material: nominal engine material.
        supports: unit 0 clamped in all DOFs.
    """

    lattice: Lattice
    design: np.ndarray
    material: Material
    supports: Supports

    @property
    def free_unit(self) -> int:
        return 1


@functools.lru_cache(maxsize=8)
def oscillation_sample(spacing_mm: float = 15.0) -> OscillationSample:
    """The spec 12.2 sample: the bottom row of a 2 x 2 square-unit lattice with its one
    horizontal ligament (the smallest `quads` lattice, cut down to two units and one bond).
    One object per spacing (cached, immutable)."""
    import dataclasses

    big = quads(2, 2, spacing=spacing_mm)
    x = periodic_design(big, 0.0)
    lat = dataclasses.replace(big, shape=(2, 1), grid_points=big.grid_points[:2],
                              base_offsets=big.base_offsets[:2], shift_index=big.shift_index[:2],
                              bonds=big.bonds[:1], bond_r0=big.bond_r0[:1],
                              cell_of_block=big.cell_of_block[:2])
    sup = Supports.from_rules(2, {(0, d): (CH_ZERO, 0.0) for d in range(3)})
    return OscillationSample(lat, x, Material.paper(big), sup)


def oscillation_config(rtol: float = 1e-8, atol: float = 1e-7):
    """Adaptive Dopri5 with forward-mode derivatives (for jacfwd), no contact."""
    from design_engine.solve.simulate import SolverConfig

    return SolverConfig(solver=diffrax.Dopri5(), rtol=rtol, atol=atol, use_contact=False,
                        adjoint=diffrax.ForwardMode())


def make_oscillation_model(sample: OscillationSample, ts_ms, config=None):
    """Factory: `rotation(material, phi0, omega0) -> theta [n_t]` of the free unit, rad (jitted).

    The unit is held at rotation `phi0` (rad, its translation in equilibrium: Newton on u, v)
    with angular velocity `omega0` (rad/ms) at t = 0 and then free; `ts_ms` [n_t] >= 0 sample
    times, ms. Differentiable in the material, phi0 and omega0. With the default `config` the
    model is kept per (sample, sample times): the simulated video and its fit share its trace.
    """
    if config is None:
        ts = np.ascontiguousarray(ts_ms, np.float64)
        return _default_oscillation_model(sample, ts.tobytes())
    return _oscillation_model(sample, ts_ms, config)


@functools.lru_cache(maxsize=8)
def _default_oscillation_model(sample: OscillationSample, ts_bytes: bytes):
    return _oscillation_model(sample, np.frombuffer(ts_bytes, np.float64), oscillation_config())


def _oscillation_model(sample: OscillationSample, ts_ms, config):
    from design_engine.solve.simulate import make_simulator

    lat = sample.lattice
    sim = make_simulator(lat, sample.supports, config)
    energy = make_energy(lat, use_contact=False)
    geom = block_geometry(lat, jnp.asarray(sample.design))
    bonds = bond_geometry(lat, geom)
    ts = jnp.asarray(ts_ms, jnp.float64)

    def held(uv, phi, mat):
        q = jnp.zeros((2, 3)).at[1, :2].set(uv).at[1, 2].set(phi)
        return energy(q, bonds, mat)

    def rotation(mat, phi0, omega0):
        ms, ps = jax.lax.stop_gradient(mat), jax.lax.stop_gradient(phi0)
        g = jax.grad(held)
        h = jax.hessian(held)

        def newton(_, z):
            return z - spd_solve(h(z, ps, ms), g(z, ps, ms))

        uv = jax.lax.stop_gradient(jax.lax.fori_loop(0, 12, newton, jnp.zeros(2)))
        h_s = jax.lax.stop_gradient(h(uv, ps, ms))
        uv = implicit_point(uv, lambda p, m: -spd_solve(h_s, g(uv, p, m)), phi0, mat)
        q0 = jnp.concatenate([uv, jnp.reshape(phi0, (1,))])
        v0 = jnp.zeros(3).at[2].set(omega0)
        sol = sim(jnp.asarray(sample.design), mat, Loading(), ts, initial=(q0, v0))
        return sol.q[:, 1, 2]

    return jax.jit(rotation)  # one program (called as it is, it ran op by op)


OSC_PARAMS = ("damping_ratio", "damping_u", "damping_theta", "k_bend", "k_shear", "k_stretch")
DEFAULT_OSC_FIT = ("damping_ratio", "k_bend")


def log_decrement(t_s, theta, min_distance: int = 12, min_fraction: float = 0.05) -> dict:
    """Damping ratio by the spec 12.2 hand method (one video).

    Subtract the mean; positive peaks at least `min_distance` frames apart and (our addition)
    above `min_fraction` of the largest, so that peaks lost in the tracking noise or shifted by
    the mean do not bend the line; linear regression
    of ln(peak) against t in ms (slope m, 1/ms); omega_d = 2 pi f_d from the largest rFFT peak
    (refined by a parabola through the log amplitudes of the peak bin and its neighbours, where
    the spec takes the bin); zeta = 1 / sqrt(1 + (omega_d / (1000 m))^2).

    Returns {"damping_ratio", "stderr" (from the slope's regression error), "frequency_hz",
    "slope_per_ms", "n_peaks", "peak_t_s", "peak_values"}.

    Raises:
        CalibrationError: fewer than 3 usable peaks.
    """
    from scipy.signal import find_peaks

    t, y = np.asarray(t_s, np.float64), np.asarray(theta, np.float64)
    y = y - y.mean()
    peaks, _ = find_peaks(y, distance=min_distance)
    peaks = peaks[y[peaks] > 0]
    if peaks.size:
        peaks = peaks[y[peaks] >= min_fraction * y[peaks].max()]
    if peaks.size < 3:
        raise CalibrationError(f"only {peaks.size} positive peaks: the log-decrement needs 3 or "
                               "more (a longer record or a larger initial rotation)")
    tp, lp = t[peaks] * 1e3, np.log(y[peaks])
    A = np.c_[tp, np.ones_like(tp)]
    coef = np.linalg.lstsq(A, lp, rcond=None)[0]
    m = coef[0]
    dof = max(tp.size - 2, 1)
    s2 = float(np.sum((A @ coef - lp) ** 2)) / dof
    sd_m = math.sqrt(s2 * np.linalg.inv(A.T @ A)[0, 0])
    dt = float(np.median(np.diff(t)))
    amp = np.abs(np.fft.rfft(y))
    k = int(np.argmax(amp[1:]) + 1)
    shift = 0.0
    if 1 <= k < amp.size - 1:
        a, b, c = np.log(amp[k - 1: k + 2] + 1e-300)
        shift = 0.5 * (a - c) / (a - 2 * b + c) if (a - 2 * b + c) != 0 else 0.0
    f_d = (k + shift) / (y.size * dt)
    w = 2 * math.pi * f_d  # rad/s
    zeta = 1.0 / math.sqrt(1.0 + (w / (1000.0 * m)) ** 2)
    dz_dm = zeta**3 * (w / 1000.0) ** 2 / m**3  # d zeta / d m
    return {"damping_ratio": zeta, "stderr": abs(dz_dm) * sd_m, "frequency_hz": f_d,
            "slope_per_ms": m, "n_peaks": int(peaks.size), "peak_t_s": t[peaks],
            "peak_values": y[peaks]}


def fit_oscillation(t_s, theta, fit=DEFAULT_OSC_FIT, start: Material | None = None,
                    sample: OscillationSample | None = None, config=None,
                    progress=None) -> Fit:
    """Fit damping (and stiffness) to a free-oscillation rotation record through the engine.

    `t_s` [n] s from the release (t[0] = the held frame), `theta` [n] the free unit's rotation,
    rad. Nuisance parameters, always fitted: `phi0` (rad, the rotation at t[0]) and `omega0`
    (rad/s). `damping_ratio` is the zeta of spec 6.3 (zeta_start is that of the start
    material's c_u): it scales the start material's c_u and c_theta together; `damping_u`, `damping_theta` fit them separately (one mode decays: only a
    combination is determined, the rest shows up in the standard errors). `extra`: the derived
    c_u, c_theta (with propagated stderr), the curves and the log-decrement estimate.
    """
    names = check_fit_names(list(fit), OSC_PARAMS, "free-oscillation")
    check_damping_names(names)
    t, y = np.asarray(t_s, np.float64), np.asarray(theta, np.float64)
    if t.ndim != 1 or t.shape != y.shape:
        raise CalibrationError("the rotation record must be two 1-D arrays of equal length")
    if t.size < 50:
        raise CalibrationError(f"only {t.size} frames; a free-oscillation fit needs 50 or more")
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(y))) or np.any(np.diff(t) <= 0):
        raise CalibrationError("the rotation record needs finite values and increasing times")
    sample = sample or oscillation_sample()
    start = start or sample.material
    lat = sample.lattice
    ts_ms = (t - t[0]) * 1e3
    model = make_oscillation_model(sample, ts_ms, config)
    zeta0 = start_damping_ratio(start, lat)
    start_si = start.to_si()
    start_si["damping_ratio"] = zeta0
    start_si["phi0"], start_si["omega0"] = float(y[0]), 0.0
    all_names = names + ["phi0", "omega0"]
    units = dict(SI_UNITS, phi0="rad", omega0="rad/s")
    material = make_fitted_material(start, names, start_si, lat)

    def curve(p):
        return model(material(p), p[len(names)], p[len(names) + 1])

    yy = jnp.asarray(y)

    def residual(p):
        return curve(p) - yy

    out = run_fit(residual, all_names, names, start_si, units, "rad", progress=progress,
                  stage="oscillation")
    p = jnp.asarray(out.extra["p"])
    m = material(p)
    # the fitted curve is the data plus the residual at the optimum (no further solve)
    out.extra["curves"] = {"t_s": t, "data": y, "fitted": np.asarray(out.extra["r"]) + y}
    if "damping_ratio" in names:
        out.extra["derived"] = derived_damping(out, m)
    try:
        out.extra["log_decrement"] = log_decrement(t, y)
        # the same hand method on the fitted (noise-free) curve: the modal zeta it implies
        out.extra["log_decrement"]["damping_ratio_of_fit"] = log_decrement(
            t, out.extra["curves"]["fitted"])["damping_ratio"]
    except CalibrationError as exc:
        out.extra["log_decrement"] = {"error": str(exc)}
    return out


