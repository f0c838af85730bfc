"""The least-squares core of every calibration: Levenberg-Marquardt on log parameters, with
Gauss-Newton (and clustered) standard errors, and the material that a fit's parameters make.

Every fit minimises sum r^2 over parameters theta = log(value / start) (positive values), by
Levenberg-Marquardt with the residual Jacobian from `jax.jacfwd` through the model (the
equilibrium by the implicit function theorem, the ODE by forward-mode through diffrax).
Standard errors: cov(theta) = s^2 (J^T J)^-1, s^2 = RSS / (n - p), mapped to the values by the
delta method (stderr = value * sd(theta)); the pulse fit adds the model error, the misfit that
the tracking noise does not explain (`pulse.model_error`). A direction the data do not see has a
tiny eigenvalue of J^T J and so a huge standard error; the fit stays near its start there.

Internal units inside (mm, ms, g); every value leaving the calibration is SI, with the names of
the engine's `Material` (k_stretch, k_shear N/m; k_bend N m/rad; damping_u N s/m; damping_theta
N m s) plus `damping_ratio` (1). The models beside it: `hinge` (spec 12.1), `oscillation`
(spec 12.2) and `pulse` (the pulse experiments themselves).
"""

import math
import time
from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np

from design_engine.physics.lattice import Lattice
from design_engine.physics.material import (SI_POWER, Material, engine_to_si, reference_damping,
                                            si_to_engine)
from design_engine.physics.material_file import SI_UNITS

# SI -> internal factors of the fitted quantities that are not material fields: the damping
# ratio (1), and the oscillation fit's nuisance initial rotation (rad) and rate (rad/s -> rad/ms).
_NUISANCE_TO_INTERNAL = {"damping_ratio": 1.0, "phi0": 1.0, "omega0": 1e-3}
STIFFNESSES = ("k_stretch", "k_shear", "k_bend")
LOG_BOUND = math.log(100.0)  # fitted values stay within a factor 100 of the start
UNDETERMINED_SD = 0.5  # sd(log value) above which a parameter counts as not determined
LARGE_SD = 1e6  # sd(log value) reported for a direction the data do not determine at all


def to_internal(name: str, x):
    """Internal value of the SI value `x` of a fitted quantity (float or traced)."""
    return si_to_engine(name, x) if name in SI_POWER else x * _NUISANCE_TO_INTERNAL[name]


def to_si(name: str, x):
    """SI value of the internal value `x` of a fitted quantity."""
    return engine_to_si(name, x) if name in SI_POWER else x / _NUISANCE_TO_INTERNAL[name]


class CalibrationError(ValueError):
    """Inputs a calibration cannot use (the message is one line saying why)."""


# --- the least-squares engine ---------------------------------------------------------------


@dataclass
class Fit:
    """Result of a least-squares fit (SI).

    Attributes:
        names: fitted parameter names (material names, then nuisance parameters).
        values, stderr: name -> fitted value and its standard error, SI.
        units: name -> SI unit.
        start: name -> start value, SI.
        rms: root-mean-square residual at the optimum (residual unit).
        sigma: residual standard deviation s = sqrt(RSS / (n - p)).
        n: number of residuals; dof: n - p.
        iterations: Levenberg-Marquardt iterations; converged: step / cost criterion met.
        correlation: [p, p] correlation matrix of the fitted parameters.
        residual_unit: unit of the residuals (N, rad, m).
        wall_s: wall time of the fit, s (compilation included).
        extra: kind-specific data (curves for plotting, derived values).
    """

    names: list
    values: dict
    stderr: dict
    units: dict
    start: dict
    rms: float
    sigma: float
    n: int
    dof: int
    iterations: int
    converged: bool
    correlation: np.ndarray
    residual_unit: str
    wall_s: float = 0.0
    extra: dict = field(default_factory=dict)

    @property
    def undetermined(self) -> list:
        """Names whose relative standard error exceeds `UNDETERMINED_SD` (the data barely see
        them: their values are start values moved by noise)."""
        return [n for n in self.names if n in SI_UNITS  # nuisance parameters are not judged
                and abs(self.stderr[n]) > UNDETERMINED_SD * abs(self.values[n])]

    def parameters_json(self) -> dict:
        """`{name: {"value", "stderr", "unit"}}` (JSON-ready)."""
        return {n: {"value": float(self.values[n]), "stderr": float(self.stderr[n]),
                    "unit": self.units[n]} for n in self.names}


MAX_STEP = 0.7  # largest change of one log parameter per iteration (a factor 2)


def levenberg_marquardt(fun, p0, *, max_iter: int = 40, xtol: float = 1e-9, ftol: float = 1e-13,
                        bound=None):
    """Minimise |r(p)|^2; `fun(p) -> (r [n], J [n, p])` (numpy). Returns (p, r, J, iters, ok).

    Marquardt scaling (diag of J^T J), steps capped at `MAX_STEP` per component and kept in
    [-bound, bound] where `bound` [n_p] is finite (a parameter the data do not see cannot run
    away to 0 or infinity, where its value-space stderr would look small); a step is accepted
    when the cost falls.
    """
    bound = np.full(len(p0), np.inf) if bound is None else np.asarray(bound, np.float64)
    p = np.asarray(p0, np.float64)
    r, J = fun(p)
    if not (np.all(np.isfinite(r)) and np.all(np.isfinite(J))):
        raise CalibrationError("the model is not finite at the start values")
    cost, lam, ok, it = float(r @ r), 1e-3, False, 0
    for it in range(1, max_iter + 1):
        A, g = J.T @ J, J.T @ r
        d = np.diag(A).copy()
        d = np.maximum(d, 1e-12 * max(d.max(), 1e-300))
        while True:
            step = -np.linalg.solve(A + lam * np.diag(d), g)
            step *= min(1.0, MAX_STEP / max(np.max(np.abs(step)), 1e-300))
            step = np.clip(p + step, -bound, bound) - p
            r_new, J_new = fun(p + step)
            c_new = float(r_new @ r_new) if np.all(np.isfinite(r_new)) else np.inf
            if c_new <= cost:
                break
            lam *= 10.0
            if lam > 1e12:
                return p, r, J, it, True  # no descent left: at the optimum to rounding
        small = np.max(np.abs(step)) < xtol or (cost - c_new) <= ftol * max(cost, 1e-300)
        p, r, J, cost, lam = p + step, r_new, J_new, c_new, max(lam / 10.0, 1e-9)
        if small:
            ok = True
            break
    return p, r, J, it, ok


def _sandwich(J, r, bread, groups) -> np.ndarray:
    """Cluster-robust (J^T J)^-1 (sum_c g_c g_c^T) (J^T J)^-1, g_c = J_c^T r_c, times G/(G-1)."""
    ids, which = np.unique(np.asarray(groups), return_inverse=True)
    g = np.zeros((ids.size, J.shape[1]))
    np.add.at(g, which, J * r[:, None])
    return bread @ (g.T @ g) @ bread * (ids.size / max(ids.size - 1, 1))


def covariance(J: np.ndarray, r: np.ndarray, clusters=None) -> tuple[np.ndarray, float, int]:
    """Covariance of the parameters, s^2 = RSS / (n - p) and the dof n - p.

    Without `clusters`: Gauss-Newton, s^2 (J^T J)^-1 (independent residuals of equal variance).
    With `clusters` [n] (a group id per residual): the cluster-robust sandwich
    (J^T J)^-1 (sum_c g_c g_c^T) (J^T J)^-1, g_c = J_c^T r_c, times G/(G-1) (n-1)/(n-p), right
    when the residuals within a group are correlated and equal to Gauss-Newton for
    independent noise. With a pair `(a, b)` of group ids per residual: two-way clustering,
    V_a + V_b - V_ab (Cameron, Gelbach and Miller), negative eigenvalues clipped to 0; for a
    tracked record, a = unit and b = time block, since the tracker's and the input's errors
    are correlated along a unit's record and across all units at one time.
    Eigen-directions of J^T J below 1e-14 of its largest eigenvalue (the data do not see them)
    get sd = LARGE_SD instead of an inverse that rounding would make arbitrary.
    """
    n, p = J.shape
    dof = max(n - p, 1)
    s2 = float(r @ r) / dof
    w, V = np.linalg.eigh(J.T @ J)
    floor = 1e-14 * max(w.max(), 1e-300)
    seen = w > floor
    bread = (V * np.where(seen, 1.0 / np.maximum(w, floor), 0.0)) @ V.T
    if clusters is None:
        cov = bread * s2
    elif isinstance(clusters, tuple):
        a, b = (np.asarray(c) for c in clusters)
        both = np.unique(np.c_[a, b], axis=0, return_inverse=True)[1].reshape(-1)
        cov = (_sandwich(J, r, bread, a) + _sandwich(J, r, bread, b)
               - _sandwich(J, r, bread, both)) * ((n - 1) / dof)
        ew, ev = np.linalg.eigh(0.5 * (cov + cov.T))
        cov = (ev * np.maximum(ew, 0.0)) @ ev.T
    else:
        cov = _sandwich(J, r, bread, clusters) * ((n - 1) / dof)
    unseen = V[:, ~seen]
    return cov + (unseen * LARGE_SD**2) @ unseen.T, s2, dof


def run_fit(residual, names: list, log_params: list, start_si: dict, units: dict,
            residual_unit: str, scale: float = 1.0, max_iter: int = 40, p0=None,
            progress=None, stage: str = "", clusters=None, residual_and_jacobian=None) -> Fit:
    """Fit `residual(p) -> r [n]` (jax, internal units) over p (log-ratio or linear per name).

    Args:
        residual: jax function of p [n_p]: log(value / start) for names in `log_params`, the
            value itself (internal units) for the others.
        names: parameter names in the order of p.
        log_params: names that are positive and fitted in log space.
        start_si: name -> start value, SI (values = start * exp(p) for log parameters).
        units: name -> SI unit.
        residual_unit: unit of `residual * scale` (the reported residual).
        scale: residual internal -> SI factor.
        p0: start point (default: the start values, p = 0 for the log parameters).
        progress: optional `progress(stage, evaluation, rms)` called after every evaluation of
            the model and its Jacobian (rms in the residual unit; inf where not finite).
        clusters: optional [n] group id per residual, or a pair of them (two-way): standard
            errors from the cluster-robust covariance (`covariance`);
            `extra["stderr_gauss_newton"]` keeps the plain ones.
        residual_and_jacobian: optional `p -> (r [n], dr/dp [n, n_p])` used instead of
            `jax.jacfwd` of `residual` (which may then be None): for models whose compiled
            programs are shared with other fits.

    `extra["r"]`: the residual at the returned p (internal units).
    """
    t0 = time.perf_counter()
    if residual_and_jacobian is None:
        def with_value(p):
            r = residual(p)
            return r, r  # the residual once: its Jacobian and (as aux) its value

        jac = jax.jit(jax.jacfwd(with_value, has_aux=True))

        def residual_and_jacobian(p):
            J, r = jac(jnp.asarray(p))
            return r, J

    count = [0]

    def fun(p):
        r, J = residual_and_jacobian(p)
        r, J = np.asarray(r, np.float64), np.asarray(J, np.float64)
        count[0] += 1
        if progress is not None:
            rms = float(np.sqrt(np.mean(r**2))) * scale if np.all(np.isfinite(r)) else math.inf
            progress(stage, count[0], rms)
        return r, J

    if p0 is None:
        p0 = np.zeros(len(names))
        for i, n in enumerate(names):
            if n not in log_params:
                p0[i] = to_internal(n, start_si[n])
    bound = np.array([LOG_BOUND if n in log_params else np.inf for n in names])
    p, r, J, iters, ok = levenberg_marquardt(fun, p0, max_iter=max_iter, bound=bound)
    cov, s2, dof = covariance(J, r, clusters)
    sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
    sd_gn = np.sqrt(np.maximum(np.diag(covariance(J, r)[0]), 0.0))
    values, stderr, stderr_gn = {}, {}, {}
    for i, n in enumerate(names):
        if n in log_params:
            values[n] = start_si[n] * math.exp(p[i])
            stderr[n] = values[n] * sd[i]  # delta method: d value = value d log value
            stderr_gn[n] = values[n] * sd_gn[i]
        else:
            values[n] = to_si(n, p[i])
            stderr[n], stderr_gn[n] = to_si(n, sd[i]), to_si(n, sd_gn[i])
    corr = cov / np.outer(np.maximum(sd, 1e-300), np.maximum(sd, 1e-300))
    return Fit(names=list(names), values=values, stderr=stderr, units=dict(units),
               start={n: start_si[n] for n in names}, rms=float(np.sqrt(np.mean(r**2))) * scale,
               sigma=math.sqrt(s2) * scale, n=int(r.size), dof=dof, iterations=iters,
               converged=ok, correlation=corr, residual_unit=residual_unit,
               wall_s=time.perf_counter() - t0,
               extra={"p": p, "r": r, "J": J, "stderr_gauss_newton": stderr_gn})


def start_damping_ratio(start: Material, lattice: Lattice) -> float:
    """The damping ratio zeta of spec 6.3 that the start material's c_u corresponds to."""
    return float(start.damping_u) / float(reference_damping(lattice, 1.0, start.density,
                                                             start.k_shear, start.k_bend)[0])


def make_fitted_material(start: Material, names: list, start_si: dict, lattice: Lattice):
    """Factory: `material(p) -> Material` with the fitted names at start * exp(p[i]) (p may hold
    further, nuisance entries after them). With `damping_ratio` fitted, c_u and c_theta follow
    spec 6.3 from zeta and the current stiffnesses (`reference_damping` on `lattice`), as a
    material file's damping ratio does."""
    def material(p):
        vals = {n: to_internal(n, start_si[n]) * jnp.exp(p[i]) for i, n in enumerate(names)}
        fields = {k: v for k, v in vals.items() if k != "damping_ratio"}
        if "damping_ratio" in vals:
            c_u, c_t = reference_damping(lattice, vals["damping_ratio"], start.density,
                                         fields.get("k_shear", start.k_shear),
                                         fields.get("k_bend", start.k_bend))
            fields["damping_u"], fields["damping_theta"] = c_u, c_t
        return start.replaced(**fields)

    return material


def derived_damping(fit: Fit, m: Material) -> dict:
    """c_u, c_theta (SI) of a fit of `damping_ratio`, with standard errors by the delta method:
    log c_u = log zeta + log k_shear / 2 + const, log c_theta = log zeta + log k_bend / 2 + const
    (spec 6.3), through the fit's correlations."""
    names = fit.names
    rel = np.array([fit.stderr[n] / fit.values[n] for n in names])
    cov = fit.correlation * np.outer(rel, rel)  # of the log values
    out = {}
    for n, k in (("damping_u", "k_shear"), ("damping_theta", "k_bend")):
        g = np.array([1.0 if a == "damping_ratio" else 0.5 if a == k else 0.0 for a in names])
        v = to_si(n, float(getattr(m, n)))
        out[n] = {"value": v, "stderr": v * math.sqrt(max(float(g @ cov @ g), 0.0)),
                  "unit": SI_UNITS[n]}
    return out


def check_damping_names(names):
    if "damping_ratio" in names and ({"damping_u", "damping_theta"} & set(names)):
        raise CalibrationError("fit either damping_ratio or damping_u / damping_theta, not both")


def check_fit_names(fit, allowed, kind):
    bad = [n for n in fit if n not in allowed]
    if bad:
        raise CalibrationError(f"cannot fit {', '.join(bad)} from a {kind} test (choose from "
                               f"{', '.join(allowed)})")
    if not fit:
        raise CalibrationError("no parameters to fit")
    return list(dict.fromkeys(fit))


