"""Material calibration: least squares through the engine, with Gauss-Newton standard errors.

Three kinds of test (spec 12.1, 12.2 and the pulse experiments themselves):
- hinge tests: quasi-static 4x6 rotating-squares sample, top row displaced (tension,
  compression, shear), bottom row fixed; the model is the equilibrium of the engine's energy
  (`make_energy`, no contact) solved by Newton with exact Hessians, the reaction force summed
  over the top row (`make_hinge_forces`). Fits `k_stretch`, `k_shear`, `k_bend`.
- free oscillation: two theta0 = 0 units joined by one ligament, one held, the other released
  from a rotation; simulated by the engine (`make_oscillation_model`). Fits the damping (a
  damping ratio zeta that scales c_u and c_theta as spec 6.3, or the two coefficients) and
  `k_bend`; `log_decrement` is the spec's hand method.
- pulse experiment: the tracked unit positions of a recorded run against the engine under the
  measured input (`fit_pulse`).

Every fit minimises sum r^2 over parameters theta = log(value / start) (positive values), by
Levenberg-Marquardt with the residual Jacobian from `jax.jacfwd` through the model (the
equilibrium by the implicit function theorem, the ODE by forward-mode through diffrax).
Standard errors: cov(theta) = s^2 (J^T J)^-1, s^2 = RSS / (n - p), mapped to the values by the
delta method (stderr = value * sd(theta)); the pulse fit adds the model error, the misfit that
the tracking noise does not explain (`model_error`). A direction the data do not see has a tiny
eigenvalue of J^T J and so a huge standard error; the fit stays near its start there.

Internal units inside (mm, ms, g); every value leaving this module is SI, with the names of the
engine's `Material` (k_stretch, k_shear N/m; k_bend N m/rad; damping_u N s/m; damping_theta
N m s) plus `damping_ratio` (1).
"""

import functools
import math
import time
from dataclasses import dataclass, field

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

from design_engine.energy import bond_geometry, make_energy
from design_engine.geometry import block_geometry
from design_engine.lattice import Lattice, periodic_design, quads
from design_engine.linalg import implicit_point, spd_solve
from design_engine.loading import CH_ZERO, Loading, Supports
from design_engine.material import SI_POWER, Material, engine_to_si, reference_damping, si_to_engine
from design_engine.material_file import SI_UNITS
from design_engine.regions import row_units

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


def _check_damping_names(names):
    if "damping_ratio" in names and ({"damping_u", "damping_theta"} & set(names)):
        raise CalibrationError("fit either damping_ratio or damping_u / damping_theta, not both")


def _check_fit_names(fit, allowed, kind):
    bad = [n for n in fit if n not in allowed]
    if bad:
        raise CalibrationError(f"cannot fit {', '.join(bad)} from a {kind} test (choose from "
                               f"{', '.join(allowed)})")
    if not fit:
        raise CalibrationError("no parameters to fit")
    return list(dict.fromkeys(fit))


# --- hinge tests (spec 12.1) ----------------------------------------------------------------

# test -> (loaded DOF of the top row: 0 u / 1 v, sign of the motion, paper's max displacement m)
HINGE_TESTS = {"tension": (1, 1.0, 1.05e-3), "compression": (1, -1.0, 3.75e-3),
               "shear": (0, 1.0, 3.75e-3)}


@dataclass(frozen=True, eq=False)
class HingeSample:
    """The hinge-test sample: nx x ny rotating squares, bottom row fixed, top row driven.

    Attributes:
        lattice, design: topology and design vector (mm).
        material: nominal engine material (internal units; only stiffnesses matter here).
        bottom, top: [nx] unit ids of the fixed and driven rows.
        free: [n_f] free global DOF ids (3 b + d) of the rows in between.
    """

    lattice: Lattice
    design: np.ndarray
    material: Material
    bottom: np.ndarray
    top: np.ndarray
    free: np.ndarray


@functools.lru_cache(maxsize=8)
def hinge_sample(nx: int = 4, ny: int = 6, bias_angle_deg: float = 20.0) -> HingeSample:
    """The spec 12.1 sample (4 x 4 free units plus a clamped row top and bottom, bias 20 deg).

    One object per set of arguments (cached, immutable): the compiled hinge-test programs
    (`make_hinge_forces`) are kept per sample, so the file generation, every fit and the plot
    share them."""
    lat = quads(nx, ny)
    x = periodic_design(lat, math.radians(bias_angle_deg))
    bottom, top = row_units(lat, 0), row_units(lat, ny - 1)
    held = {int(b) for b in np.r_[bottom, top]}
    free = np.array([3 * b + d for b in range(lat.n_blocks) if b not in held for d in range(3)])
    return HingeSample(lat, x, Material.paper(lat), bottom, top, free)


def make_hinge_forces(sample: HingeSample, test: str, newton_steps: int = 3):
    """Factory: `forces(k [3], d_mm [n]) -> F [n]` reaction force of the test, N (jitted), with
    `forces.with_jacobian(k, d_mm) -> (F [n], dF/dk [n, 3])` (jitted, forward mode).

    `k` = (k_stretch N/mm, k_shear N/mm, k_bend N mm/rad); `d_mm` = displacement magnitudes,
    increasing from 0 in small steps, mm. Quasi-static path following: at each displacement
    Newton's method (exact Hessian, `newton_steps` steps from a secant prediction) on the free
    DOFs, then one Newton correction with frozen Hessian that carries the implicit derivative
    dq/dk (exact at an equilibrium). The
    force is the sum over the top row of dV/dq on the loaded DOF times the sign of the motion
    (spec 12.1: +1, -1, +1 for tension, compression, shear), so every test reads positive.

    The three tests run one compiled program per sample (the loaded DOFs and the sign are its
    arguments), kept per (sample, newton_steps) (samples compare by identity): the generation
    of test files, every fit and their plots share it.
    """
    if test not in HINGE_TESTS:
        raise CalibrationError(f"unknown hinge test {test!r} (choose from {', '.join(HINGE_TESTS)})")
    dof, sign, _ = HINGE_TESTS[test]
    forces_j, with_jacobian_j = _hinge_programs(sample, newton_steps)
    loaded = jnp.asarray(3 * np.asarray(sample.top) + dof)
    sign = jnp.asarray(sign, jnp.float64)

    def forces(k, d_mm):
        return forces_j(k, d_mm, loaded, sign)

    def with_jacobian(k, d_mm):
        return with_jacobian_j(k, d_mm, loaded, sign)

    forces.with_jacobian = with_jacobian
    return forces


@functools.lru_cache(maxsize=16)
def _hinge_programs(sample: HingeSample, newton_steps: int):
    """The jitted `forces(k, d_mm, loaded, sign)` and `with_jacobian(...)` of a sample
    (`make_hinge_forces`): `loaded` [nx] the driven DOF ids of the top row, `sign` +-1."""
    lat = sample.lattice
    energy = make_energy(lat, use_contact=False)
    geom = block_geometry(lat, jnp.asarray(sample.design))
    bonds = bond_geometry(lat, geom)
    free = jnp.asarray(sample.free)
    nb = lat.n_blocks

    def full(qf, d, loaded, sign):
        return jnp.zeros(3 * nb, qf.dtype).at[free].set(qf).at[loaded].set(sign * d)

    def total(qfull, k):
        mat = sample.material.replaced(**dict(zip(STIFFNESSES, (k[0], k[1], k[2]))))
        return energy(qfull.reshape(nb, 3), bonds, mat)

    def grad_f(qf, d, k, loaded, sign):
        return jax.grad(lambda z: total(full(z, d, loaded, sign), k))(qf)

    def hess_f(qf, d, k, loaded, sign):
        return jax.hessian(lambda z: total(full(z, d, loaded, sign), k))(qf)

    def path(k, d_mm, loaded, sign):
        """[n, n_f] equilibria along the ramp (no derivatives), secant predictor + Newton."""
        def step(carry, d):
            q1, q2 = carry
            def newton(_, z):
                return z - spd_solve(hess_f(z, d, k, loaded, sign), grad_f(z, d, k, loaded, sign))

            q = jax.lax.fori_loop(0, newton_steps, newton, 2.0 * q1 - q2)
            return (q, q1), q

        z = jnp.zeros(free.size)
        return jax.lax.scan(step, (z, z), d_mm)[1]

    def force_at(qs, d, k, loaded, sign):
        h = jax.lax.stop_gradient(hess_f(qs, d, jax.lax.stop_gradient(k), loaded, sign))
        qd = implicit_point(qs, -spd_solve(h, grad_f(qs, d, k, loaded, sign)))
        g = jax.grad(lambda qq: total(qq, k))(full(qd, d, loaded, sign))
        return sign * jnp.sum(g[loaded])

    def forces(k, d_mm, loaded, sign):
        k = jnp.asarray(k, jnp.float64)
        d_mm = jnp.asarray(d_mm, jnp.float64)
        qs = path(jax.lax.stop_gradient(k), d_mm, loaded, sign)  # the path carries no derivative
        return jax.vmap(force_at, in_axes=(0, 0, None, None, None))(qs, d_mm, k, loaded, sign)

    def with_jacobian(k, d_mm, loaded, sign):
        def both(kk):
            f = forces(kk, d_mm, loaded, sign)
            return f, f

        jac, f = jax.jacfwd(both, has_aux=True)(jnp.asarray(k, jnp.float64))
        return f, jac

    return jax.jit(forces), jax.jit(with_jacobian)


@dataclass(frozen=True)
class HingeRecord:
    """One hinge-test run: test name, displacement magnitudes (m) and forces (N), time (s)."""

    test: str
    t_s: np.ndarray
    d_m: np.ndarray
    f_n: np.ndarray
    path: str = ""


HINGE_HEADER = ("metarig simulated Instron hinge test",
                ("test={test}; sample={nx}x{ny} rotating squares, bias {bias:g} deg; "
                 "noise_N={noise:g}; seed={seed}"),
                "Time (s),Extension (m),Load (N)")
MIN_POINTS = 10


def read_hinge_file(path, test: str | None = None) -> HingeRecord:
    """Read an Instron-style file: 3 header lines, then comma-separated time s, displacement m,
    force N. The test is `test`, else `test=NAME` in the header, else a test name in the file
    name. Displacements are taken as magnitudes (a compression file may be signed).

    Raises:
        CalibrationError: unreadable, malformed rows, not 3 columns, too few points, no test.
    """
    from pathlib import Path

    path = Path(path)
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise CalibrationError(f"{path}: cannot read the hinge-test file ({exc})") from None
    if len(lines) < 4:
        raise CalibrationError(f"{path}: a hinge-test file needs 3 header lines and data rows, "
                               f"got {len(lines)} lines")
    head = " ".join(lines[:3]).lower()
    if test is None:
        for name in HINGE_TESTS:
            if f"test={name}" in head:
                test = name
        if test is None:
            hits = [n for n in HINGE_TESTS if n in path.name.lower()]
            test = hits[0] if len(hits) == 1 else None
    if test is None:
        raise CalibrationError(f"{path}: which hinge test is it? put tension, compression or shear "
                               "in the file name or 'test=NAME' in the header")
    rows = []
    for i, line in enumerate(lines[3:], start=4):
        if not line.strip():
            continue
        cells = [c.strip().strip('"') for c in line.split(",")]
        if len(cells) != 3:
            raise CalibrationError(f"{path}: line {i} has {len(cells)} columns; expected 3 "
                                   "(time s, displacement m, force N)")
        try:
            rows.append([float(c) for c in cells])
        except ValueError:
            raise CalibrationError(f"{path}: line {i} is not numeric: {line.strip()[:60]!r}") from None
    a = np.asarray(rows, np.float64).reshape(-1, 3)
    if a.shape[0] < MIN_POINTS:
        raise CalibrationError(f"{path}: only {a.shape[0]} data rows; a hinge fit needs "
                               f"{MIN_POINTS} or more")
    if not np.all(np.isfinite(a)):
        raise CalibrationError(f"{path}: non-finite values in the data")
    d = np.abs(a[:, 1])
    if d.max() <= 0 or d.max() > 0.05:
        raise CalibrationError(f"{path}: displacements must be in m and span (0, 0.05] m, got "
                               f"max {d.max():.3g}")
    return HingeRecord(test, a[:, 0], d, np.abs(a[:, 2]), str(path))


def hinge_grid(rec: HingeRecord, n_max: int = 200) -> tuple[np.ndarray, np.ndarray]:
    """The run's force on min(n, n_max) evenly spaced displacements over its range (spec 12.1:
    interpolate each run on an even grid): (d_m [k], f_N [k])."""
    order = np.argsort(rec.d_m, kind="stable")
    d, f = rec.d_m[order], rec.f_n[order]
    d, keep = np.unique(d, return_index=True)
    f = f[keep]
    k = min(d.size, n_max)
    grid = np.linspace(max(d[0], 0.0), d[-1], k)
    return grid, np.interp(grid, d, f)


def fit_hinge(records: list, fit=STIFFNESSES, start: Material | None = None,
              sample: HingeSample | None = None, n_grid: int = 200, progress=None) -> Fit:
    """Fit ligament stiffnesses to hinge-test runs (any mix of tests and repeats).

    Residuals: model force minus measured force (N) on each run's even displacement grid.
    `start`: start material (default the sample's nominal one). `extra["curves"]`: per run
    (test, d_m, measured N, fitted N, start N) for plotting.
    """
    names = _check_fit_names(list(fit), STIFFNESSES, "hinge")
    sample = sample or hinge_sample()
    start = start or sample.material
    k0 = np.asarray([float(getattr(start, n)) for n in STIFFNESSES], np.float64)
    models = {t: make_hinge_forces(sample, t).with_jacobian for t in {r.test for r in records}}
    grids = [hinge_grid(r, n_grid) for r in records]
    idx = np.asarray([STIFFNESSES.index(n) for n in names])

    def model(p):
        """Per run: (force [k], d force / d p [k, n_p]); p = log(k / k0) at `idx`. The path
        starts from rest: its first point is d = 0 (dropped)."""
        lk = np.zeros(3)
        lk[idx] = p
        k = k0 * np.exp(lk)
        out = []
        for r, g in zip(records, grids):
            f, dk = models[r.test](k, np.r_[0.0, g[0] * 1e3])
            out.append((np.asarray(f, np.float64)[1:],
                        np.asarray(dk, np.float64)[1:, idx] * k[idx]))  # d k / d p = k
        return out

    def residual_and_jacobian(p):
        m = model(np.asarray(p, np.float64))
        return (np.concatenate([f - g[1] for (f, _), g in zip(m, grids)]),
                np.concatenate([j for _, j in m]))

    start_si = start.to_si()
    out = run_fit(None, names, names, start_si, SI_UNITS, "N", progress=progress,
                  stage="hinge", residual_and_jacobian=residual_and_jacobian)
    fitted, first = model(out.extra["p"]), model(np.zeros(len(names)))
    out.extra["curves"] = [(r.test, g[0], g[1], f[0], s[0])
                           for r, g, f, s in zip(records, grids, fitted, first)]
    return out


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
    from design_engine.simulate import SolverConfig

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
    from design_engine.simulate import make_simulator

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
        uv = implicit_point(uv, -spd_solve(jax.lax.stop_gradient(h(uv, ps, ms)), g(uv, phi0, mat)))
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
    names = _check_fit_names(list(fit), OSC_PARAMS, "free-oscillation")
    _check_damping_names(names)
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
    from design_engine.simulate import SolverConfig

    return SolverConfig(solver=diffrax.Dopri8(), adjoint=diffrax.ForwardMode())


def pulse_config(scene):
    """Fixed-step Verlet at the automatic step, float64, with contact (for jacfwd): on the
    24x16 focusing design in contact under a 7.5 mm pulse its motion lies within 0.5 um of
    adaptive Dopri8 at the reference tolerances, 8x faster; without contact it is 195 um off.
    Pre-compressed scenes get `contact_forward_config()` (Dopri8)."""
    from design_engine.auto import choose_config
    from design_engine.simulate import SolverConfig

    choice = choose_config(scene)
    if choice.config.use_contact:
        return contact_forward_config()
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
            `design_engine.run.smooth_input` does), starting at rest.
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
    from design_engine.fixed_step import is_fixed_step
    from design_engine.run import measured_loading
    from design_engine.simulate import make_simulator

    names = _check_fit_names(list(fit), PULSE_PARAMS, "pulse")
    _check_damping_names(names)
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

    automatic = config is None
    config = config or pulse_config(scene)
    t0 = time.perf_counter()
    try:
        out, simulate = continuation(config)
    except CalibrationError:  # not finite at the start (fixed step unstable in contact)
        if not automatic or not is_fixed_step(config.solver):
            raise
        config = contact_forward_config()
        out, simulate = continuation(config)
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


__all__ = [
    "HINGE_TESTS",
    "CalibrationError",
    "Fit",
    "HingeRecord",
    "HingeSample",
    "OscillationSample",
    "covariance",
    "fit_hinge",
    "fit_oscillation",
    "fit_pulse",
    "hinge_sample",
    "levenberg_marquardt",
    "log_decrement",
    "make_hinge_forces",
    "make_oscillation_model",
    "to_internal",
    "to_si",
    "oscillation_sample",
    "pulse_config",
    "read_hinge_file",
    "run_fit",
]
