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
delta method (stderr = value * sd(theta)). A direction the data do not see has a tiny
eigenvalue of J^T J and so a huge standard error; the fit stays near its start there.

Internal units inside (mm, ms, g); every value leaving this module is SI, with the names of the
engine's `Material` (k_stretch, k_shear N/m; k_bend N m/rad; damping_u N s/m; damping_theta
N m s) plus `damping_ratio` (1).
"""

import math
import time
from dataclasses import dataclass, field

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from design_engine.energy import bond_geometry, make_energy
from design_engine.geometry import block_geometry
from design_engine.lattice import Lattice, periodic_design, quads
from design_engine.loading import CH_ZERO, Loading, Supports
from design_engine.material import Material
from design_engine.regions import row_units


# SI value * factor = internal value
TO_INTERNAL = {"k_stretch": 1e-3, "k_shear": 1e-3, "k_bend": 1e3, "k_contact": 1e3,
               "damping_u": 1.0, "damping_theta": 1e6, "damping_ratio": 1.0,
               "phi0": 1.0, "omega0": 1e-3}  # nuisance: initial rotation rad, rate rad/s
SI_UNITS = {"k_stretch": "N/m", "k_shear": "N/m", "k_bend": "N m/rad", "k_contact": "N m/rad",
            "damping_u": "N s/m", "damping_theta": "N m s", "damping_ratio": "1"}
STIFFNESSES = ("k_stretch", "k_shear", "k_bend")
LOG_BOUND = math.log(100.0)  # fitted values stay within a factor 100 of the start
UNDETERMINED_SD = 0.5  # sd(log value) above which a parameter counts as not determined
LARGE_SD = 1e6  # sd(log value) reported for a direction the data do not determine at all


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
        return [n for n in self.names if self.units[n] != "rad" and n not in ("omega0",)
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


def covariance(J: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, float, int]:
    """Gauss-Newton covariance s^2 (J^T J)^-1 of the parameters, s^2 and the dof n - p.

    Eigen-directions of J^T J below 1e-14 of its largest eigenvalue (the data do not see them)
    get sd = LARGE_SD instead of an inverse that rounding would make arbitrary.
    """
    n, p = J.shape
    dof = max(n - p, 1)
    s2 = float(r @ r) / dof
    w, V = np.linalg.eigh(J.T @ J)
    floor = 1e-14 * max(w.max(), 1e-300)
    inv = np.where(w > floor, 1.0 / np.maximum(w, floor), LARGE_SD**2 / s2 if s2 > 0 else LARGE_SD**2)
    return (V * inv) @ V.T * s2, s2, dof


def run_fit(residual, names: list, log_params: list, start_si: dict, units: dict,
            residual_unit: str, scale: float = 1.0, max_iter: int = 40) -> Fit:
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
    """
    t0 = time.perf_counter()
    jac = jax.jit(jax.jacfwd(lambda p: (residual(p), residual(p)), has_aux=True))

    def fun(p):
        J, r = jac(jnp.asarray(p))
        return np.asarray(r, np.float64), np.asarray(J, np.float64)

    p0 = np.zeros(len(names))
    for i, n in enumerate(names):
        if n not in log_params:
            p0[i] = start_si[n] * TO_INTERNAL.get(n, 1.0)
    bound = np.array([LOG_BOUND if n in log_params else np.inf for n in names])
    p, r, J, iters, ok = levenberg_marquardt(fun, p0, max_iter=max_iter, bound=bound)
    cov, s2, dof = covariance(J, r)
    sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
    values, stderr = {}, {}
    for i, n in enumerate(names):
        if n in log_params:
            values[n] = start_si[n] * math.exp(p[i])
            stderr[n] = values[n] * sd[i]  # delta method: d value = value d log value
        else:
            values[n] = p[i] / TO_INTERNAL.get(n, 1.0)
            stderr[n] = sd[i] / TO_INTERNAL.get(n, 1.0)
    corr = cov / np.outer(np.maximum(sd, 1e-300), np.maximum(sd, 1e-300))
    return Fit(names=list(names), values=values, stderr=stderr, units=dict(units),
               start={n: start_si[n] for n in names}, rms=float(np.sqrt(np.mean(r**2))) * scale,
               sigma=math.sqrt(s2) * scale, n=int(r.size), dof=dof, iterations=iters,
               converged=ok, correlation=corr, residual_unit=residual_unit,
               wall_s=time.perf_counter() - t0, extra={"p": p, "residuals": r * scale})


def _material_with(base: Material, internal: dict) -> Material:
    """`base` with the given fields (internal units, possibly traced) replaced."""
    names = tuple(internal)
    if not names:
        return base
    return eqx.tree_at(lambda m: tuple(getattr(m, n) for n in names), base,
                       tuple(internal[n] for n in names))


def material_si(m: Material) -> dict:
    """SI values of the fittable fields of an engine material."""
    return {n: float(getattr(m, n)) / TO_INTERNAL[n]
            for n in ("k_stretch", "k_shear", "k_bend", "damping_u", "damping_theta")}


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


def hinge_sample(nx: int = 4, ny: int = 6, bias_angle_deg: float = 20.0) -> HingeSample:
    """The spec 12.1 sample (4 x 4 free units plus a clamped row top and bottom, bias 20 deg)."""
    lat = quads(nx, ny)
    x = periodic_design(lat, math.radians(bias_angle_deg))
    bottom, top = row_units(lat, 0), row_units(lat, ny - 1)
    held = set(int(b) for b in np.r_[bottom, top])
    free = np.array([3 * b + d for b in range(lat.n_blocks) if b not in held for d in range(3)])
    return HingeSample(lat, x, Material.paper(lat), bottom, top, free)


def make_hinge_forces(sample: HingeSample, test: str, newton_steps: int = 3):
    """Factory: `forces(k [3], d_mm [n]) -> F [n]` reaction force of the test, N.

    `k` = (k_stretch N/mm, k_shear N/mm, k_bend N mm/rad); `d_mm` = displacement magnitudes,
    increasing from 0 in small steps, mm. Quasi-static path following: at each displacement
    Newton's method (exact Hessian, `newton_steps` steps from a secant prediction) on the free
    DOFs, then one Newton correction with frozen Hessian that carries the implicit derivative
    dq/dk (exact at an equilibrium). The
    force is the sum over the top row of dV/dq on the loaded DOF times the sign of the motion
    (spec 12.1: +1, -1, +1 for tension, compression, shear), so every test reads positive.
    """
    if test not in HINGE_TESTS:
        raise CalibrationError(f"unknown hinge test {test!r} (choose from {', '.join(HINGE_TESTS)})")
    dof, sign, _ = HINGE_TESTS[test]
    lat = sample.lattice
    energy = make_energy(lat, use_contact=False)
    geom = block_geometry(lat, jnp.asarray(sample.design))
    bonds = bond_geometry(lat, geom)
    free = jnp.asarray(sample.free)
    loaded = jnp.asarray(3 * np.asarray(sample.top) + dof)
    nb = lat.n_blocks

    def full(qf, d):
        return jnp.zeros(3 * nb, qf.dtype).at[free].set(qf).at[loaded].set(sign * d)

    def total(qfull, k):
        mat = _material_with(sample.material, dict(zip(STIFFNESSES, (k[0], k[1], k[2]))))
        return energy(qfull.reshape(nb, 3), bonds, mat)

    def grad_f(qf, d, k):
        return jax.grad(lambda z: total(full(z, d), k))(qf)

    def hess_f(qf, d, k):
        return jax.hessian(lambda z: total(full(z, d), k))(qf)

    @jax.jit
    def path(k, d_mm):
        """[n, n_f] equilibria along the ramp (no derivatives), secant predictor + Newton."""
        def step(carry, d):
            q1, q2 = carry
            def newton(_, z):
                return z - jnp.linalg.solve(hess_f(z, d, k), grad_f(z, d, k))

            q = jax.lax.fori_loop(0, newton_steps, newton, 2.0 * q1 - q2)
            return (q, q1), q

        z = jnp.zeros(free.size)
        return jax.lax.scan(step, (z, z), d_mm)[1]

    @jax.custom_jvp
    def path_const(k, d_mm):  # the path as a constant for differentiation (see force_at)
        return path(k, d_mm)

    @path_const.defjvp
    def _path_jvp(primals, tangents):
        out = path(*primals)
        return out, jnp.zeros_like(out)

    def force_at(qs, d, k):
        h = jax.lax.stop_gradient(hess_f(qs, d, jax.lax.stop_gradient(k)))
        qd = qs - jnp.linalg.solve(h, grad_f(qs, d, k))  # = qs; its derivative: the implicit one
        g = jax.grad(lambda qq: total(qq, k))(full(qd, d))
        return sign * jnp.sum(g[loaded])

    def forces(k, d_mm):
        k = jnp.asarray(k, jnp.float64)
        d_mm = jnp.asarray(d_mm, jnp.float64)
        qs = path_const(jax.lax.stop_gradient(k), d_mm)
        return jax.vmap(force_at, in_axes=(0, 0, None))(qs, d_mm, k)

    return forces


@dataclass(frozen=True)
class HingeRecord:
    """One hinge-test run: test name, displacement magnitudes (m) and forces (N), time (s)."""

    test: str
    t_s: np.ndarray
    d_m: np.ndarray
    f_n: np.ndarray
    path: str = ""


HINGE_HEADER = ("metarig simulated Instron hinge test", "test={test}; sample={nx}x{ny} rotating "
                "squares, bias {bias:g} deg; noise_N={noise:g}; seed={seed}",
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
              sample: HingeSample | None = None, n_grid: int = 200) -> Fit:
    """Fit ligament stiffnesses to hinge-test runs (any mix of tests and repeats).

    Residuals: model force minus measured force (N) on each run's even displacement grid.
    `start`: start material (default the sample's nominal one). `extra["curves"]`: per run
    (test, d_m, measured N, fitted N, start N) for plotting.
    """
    names = _check_fit_names(list(fit), STIFFNESSES, "hinge")
    sample = sample or hinge_sample()
    start = start or sample.material
    k0 = jnp.asarray([getattr(start, n) for n in STIFFNESSES])
    models = {t: make_hinge_forces(sample, t) for t in {r.test for r in records}}
    grids = [hinge_grid(r, n_grid) for r in records]
    idx = jnp.asarray([STIFFNESSES.index(n) for n in names])

    def stiff(p):
        return k0 * jnp.exp(jnp.zeros(3).at[idx].set(p))

    def model(p):
        k = stiff(p)
        return [models[r.test](k, np.r_[0.0, g[0] * 1e3])[1:] for r, g in zip(records, grids)]

    def residual(p):
        return jnp.concatenate([m - g[1] for m, g in zip(model(p), grids)])

    start_si = material_si(start)
    out = run_fit(residual, names, names, start_si, SI_UNITS, "N")
    fitted, first = model(jnp.asarray(out.extra["p"])), model(jnp.zeros(len(names)))
    out.extra["curves"] = [(r.test, g[0], g[1], np.asarray(f), np.asarray(s))
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


def oscillation_sample(spacing_mm: float = 15.0) -> OscillationSample:
    lat = quads(2, 1, spacing=spacing_mm)
    sup = Supports.from_rules(2, {(0, d): (CH_ZERO, 0.0) for d in range(3)})
    return OscillationSample(lat, periodic_design(lat, 0.0), Material.paper(lat), sup)


def ratio_damping(sample_lattice: Lattice, zeta, density, k_shear, k_bend):
    """(c_u g/ms, c_theta g mm^2/ms) of damping ratio zeta (spec 6.3), jax-traceable."""
    s = sample_lattice.spacing
    c_u = 2.0 * zeta * jnp.sqrt(density * sample_lattice.unit_area_hat * s**2 * k_shear)
    c_t = 2.0 * zeta * jnp.sqrt(density * sample_lattice.unit_inertia_hat * s**4 * k_bend)
    return c_u, c_t


def oscillation_config(rtol: float = 1e-8, atol: float = 1e-7):
    """Adaptive Dopri5 with forward-mode derivatives (for jacfwd), no contact."""
    from design_engine.simulate import SolverConfig

    return SolverConfig(solver=diffrax.Dopri5(), rtol=rtol, atol=atol, use_contact=False,
                        adjoint=diffrax.ForwardMode())


def make_oscillation_model(sample: OscillationSample, ts_ms, config=None):
    """Factory: `rotation(material, phi0, omega0) -> theta [n_t]` of the free unit, rad.

    The unit is held at rotation `phi0` (rad, its translation in equilibrium: Newton on u, v)
    with angular velocity `omega0` (rad/ms) at t = 0 and then free; `ts_ms` [n_t] >= 0 sample
    times, ms. Differentiable in the material, phi0 and omega0.
    """
    from design_engine.simulate import make_simulator

    lat = sample.lattice
    sim = make_simulator(lat, sample.supports, config or oscillation_config())
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
            return z - jnp.linalg.solve(h(z, ps, ms), g(z, ps, ms))

        uv = jax.lax.stop_gradient(jax.lax.fori_loop(0, 12, newton, jnp.zeros(2)))
        uv = uv - jnp.linalg.solve(jax.lax.stop_gradient(h(uv, ps, ms)), g(uv, phi0, mat))
        q0 = jnp.concatenate([uv, jnp.reshape(phi0, (1,))])
        v0 = jnp.zeros(3).at[2].set(omega0)
        sol = sim(jnp.asarray(sample.design), mat, Loading(), ts, initial=(q0, v0))
        return sol.q[:, 1, 2]

    return rotation


OSC_PARAMS = ("damping_ratio", "damping_u", "damping_theta", "k_bend", "k_shear", "k_stretch")
DEFAULT_OSC_FIT = ("damping_ratio", "k_bend")


def log_decrement(t_s, theta, min_distance: int = 12) -> dict:
    """Damping ratio by the spec 12.2 hand method (one video).

    Subtract the mean; positive peaks at least `min_distance` frames apart; linear regression
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
    if peaks.size < 3:
        raise CalibrationError(f"only {peaks.size} positive peaks: the log-decrement needs 3 or "
                               "more (a longer record or a larger initial rotation)")
    tp, lp = t[peaks] * 1e3, np.log(y[peaks])
    A = np.c_[tp, np.ones_like(tp)]
    coef, res, *_ = np.linalg.lstsq(A, lp, rcond=None)
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
                    sample: OscillationSample | None = None, config=None) -> Fit:
    """Fit damping (and stiffness) to a free-oscillation rotation record through the engine.

    `t_s` [n] s from the release (t[0] = the held frame), `theta` [n] the free unit's rotation,
    rad. Nuisance parameters, always fitted: `phi0` (rad, the rotation at t[0]) and `omega0`
    (rad/s). `damping_ratio` scales c_u and c_theta together as spec 6.3 (with the current
    k_shear, k_bend); `damping_u`, `damping_theta` fit them separately (one mode decays: only a
    combination is determined, the rest shows up in the standard errors). `extra`: the derived
    c_u, c_theta (with propagated stderr), the curves and the log-decrement estimate.
    """
    names = _check_fit_names(list(fit), OSC_PARAMS, "free-oscillation")
    if "damping_ratio" in names and ({"damping_u", "damping_theta"} & set(names)):
        raise CalibrationError("fit either damping_ratio or damping_u / damping_theta, not both")
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
    zeta0 = float(start.damping_u) / float(ratio_damping(lat, 1.0, start.density, start.k_shear,
                                                          start.k_bend)[0])
    start_si = material_si(start)
    start_si["damping_ratio"] = zeta0
    start_si["phi0"], start_si["omega0"] = float(y[0]), 0.0
    all_names = names + ["phi0", "omega0"]
    units = dict(SI_UNITS, phi0="rad", omega0="rad/s")

    def material(p):
        vals = {n: start_si[n] * TO_INTERNAL[n] * jnp.exp(p[i]) for i, n in enumerate(names)}
        ks = vals.get("k_shear", start.k_shear)
        kb = vals.get("k_bend", start.k_bend)
        fields = {k: v for k, v in vals.items() if k != "damping_ratio"}
        if "damping_ratio" in vals:
            fields["damping_u"], fields["damping_theta"] = ratio_damping(
                lat, vals["damping_ratio"], start.density, ks, kb)
        return _material_with(start, fields)

    def curve(p):
        return model(material(p), p[len(names)], p[len(names) + 1])

    yy = jnp.asarray(y)

    def residual(p):
        return curve(p) - yy

    out = run_fit(residual, all_names, names, start_si, units, "rad")
    p = jnp.asarray(out.extra["p"])
    m = material(p)
    out.extra["curves"] = {"t_s": t, "data": y, "fitted": np.asarray(curve(p))}
    out.extra["material"] = m
    if "damping_ratio" in names:  # derived coefficients, stderr by the chain rule
        rel = out.stderr["damping_ratio"] / out.values["damping_ratio"]
        for n in ("damping_u", "damping_theta"):
            out.extra.setdefault("derived", {})[n] = {
                "value": float(getattr(m, n)) / TO_INTERNAL[n],
                "stderr": float(getattr(m, n)) / TO_INTERNAL[n] * rel, "unit": SI_UNITS[n]}
    try:
        out.extra["log_decrement"] = log_decrement(t, y)
    except CalibrationError as exc:
        out.extra["log_decrement"] = {"error": str(exc)}
    return out


# --- pulse experiments ------------------------------------------------------------------------

PULSE_PARAMS = ("k_stretch", "k_shear", "k_bend", "damping_u", "damping_theta")
DEFAULT_PULSE_FIT = ("k_shear", "k_bend", "damping_u", "damping_theta")


def pulse_config(scene):
    """float64 fixed-step Verlet at the automatic step (no contact), for jacfwd; the scenes with
    pre-compression get adaptive Dopri8 with contact and forward-mode derivatives."""
    from design_engine.auto import choose_config
    from design_engine.simulate import SolverConfig

    choice = choose_config(scene)
    if choice.config.use_contact:
        return SolverConfig(solver=diffrax.Dopri8(), adjoint=diffrax.ForwardMode())
    return SolverConfig(solver=choice.config.solver, use_contact=False, dtype="float64")


def fit_pulse(scene, frame_t_s, tracked_q, valid, input_t_s, input_u_m, stage_t_s=None,
              stage_closing_m=None, fit=DEFAULT_PULSE_FIT, start: Material | None = None,
              config=None, units=None) -> Fit:
    """Fit material constants to a recorded pulse experiment through the engine.

    Args:
        scene: the nominal scene of the recorded design.
        frame_t_s: [n_t] frame times on the rig clock, s (> 0, increasing).
        tracked_q: [n_t, n_units, 3] tracked displacement (m, rad); only u, v are fitted, each
            relative to its first frame.
        valid: [n_t, n_units] where the tracked pose holds.
        input_t_s, input_u_m: the measured input (rig clock; smooth it first, as
            `comparison.experiment.smooth_input` does), starting at rest.
        stage_t_s, stage_closing_m: the stage closing from rest (or None).
        fit: parameter names; start: start material (default the scene's).
        config: solver configuration (default `pulse_config(scene)`).
        units: optional subset of unit ids whose motion is fitted (default all tracked).
    """
    from design_engine.simulate import make_simulator

    names = _check_fit_names(list(fit), PULSE_PARAMS, "pulse")
    ts_ms = np.asarray(frame_t_s, np.float64) * 1e3
    q = np.asarray(tracked_q, np.float64)
    ok = np.asarray(valid, bool) & np.all(np.isfinite(q), axis=-1)
    if q.ndim != 3 or q.shape[0] != ts_ms.size or q.shape[1] != scene.n_units:
        raise CalibrationError(f"tracked poses {q.shape} do not match {ts_ms.size} frames x "
                               f"{scene.n_units} units")
    if ts_ms.size < 5 or np.any(np.diff(ts_ms) <= 0) or ts_ms[0] <= 0:
        raise CalibrationError("a pulse fit needs 5 or more frames at increasing times > 0")
    use = ok & ok[:1]  # relative to the first frame: both must be tracked
    if units is not None:
        mask = np.zeros(scene.n_units, bool)
        mask[np.asarray(units)] = True
        use &= mask[None]
    use[:, np.asarray(scene.input_units)] = False  # the driven units are the input, not data
    if use.sum() < 10:
        raise CalibrationError("fewer than 10 tracked unit poses to fit")
    st = np.array([0.0, 1.0]) if stage_t_s is None else np.asarray(stage_t_s) * 1e3
    sc = np.zeros(2) if stage_t_s is None else np.asarray(stage_closing_m) * 1e3
    loading = Loading(waveform="measured", amplitude=0.0, frequency=scene.loading.frequency,
                      delay=0.0, pulse_start=0.0, strain=0.0,
                      stage_height=scene.loading.stage_height,
                      measured_t=jnp.asarray(np.asarray(input_t_s) * 1e3),
                      measured_u=jnp.asarray(np.asarray(input_u_m) * 1e3),
                      stage_t=jnp.asarray(st), stage_closing=jnp.asarray(sc))
    config = config or pulse_config(scene)
    sim = make_simulator(scene.lattice, scene.supports, config, ts_ms)
    start = start or scene.material
    start_si = material_si(start)
    data = jnp.asarray(np.where(use[..., None], (q - q[:1])[..., :2] * 1e3, 0.0))
    w = jnp.asarray(use[..., None].repeat(2, axis=-1).astype(np.float64))
    idx = np.nonzero(w.reshape(-1))[0]
    x = jnp.asarray(scene.design)
    tsj = jnp.asarray(ts_ms)

    def simulate(p):
        fields = {n: start_si[n] * TO_INTERNAL[n] * jnp.exp(p[i]) for i, n in enumerate(names)}
        sol = sim(x, _material_with(start, fields), loading, tsj)
        return sol

    def residual(p):
        qs = simulate(p).q[..., :2]
        return (qs - qs[:1] - data).reshape(-1)[idx]

    out = run_fit(residual, names, names, start_si, SI_UNITS, "m", scale=1e-3, max_iter=20)
    sol = simulate(jnp.asarray(out.extra["p"]))
    out.extra["min_void_margin"] = float(sol.min_void_margin)
    out.extra["needs_contact"] = bool(
        not config.use_contact
        and float(sol.min_void_margin) < float(start.contact_cutoff - start.contact_min))
    qs = np.asarray(sol.q)
    q0 = np.asarray(simulate(jnp.zeros(len(names))).q)
    out.extra["curves"] = {"t_s": ts_ms / 1e3, "data": q - q[:1], "fitted": qs - qs[:1],
                           "start": q0 - q0[:1], "used": use}
    return out


__all__ = ["CalibrationError", "Fit", "HINGE_TESTS", "HingeRecord", "HingeSample", "hinge_sample",
           "make_hinge_forces", "read_hinge_file", "fit_hinge", "OscillationSample",
           "oscillation_sample", "make_oscillation_model", "log_decrement", "fit_oscillation",
           "fit_pulse", "pulse_config", "levenberg_marquardt", "covariance", "run_fit",
           "material_si", "SI_UNITS", "TO_INTERNAL"]
