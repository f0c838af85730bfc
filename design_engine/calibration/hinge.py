"""Hinge tests (spec 12.1): a quasi-static 4x6 rotating-squares sample, top row displaced
(tension, compression, shear), bottom row fixed; the model is the equilibrium of the engine's
energy (`make_energy`, no contact) solved by Newton with exact Hessians, the reaction force
summed over the top row (`make_hinge_forces`). Fits `k_stretch`, `k_shear`, `k_bend`; reads the
Instron-style record files (`read_hinge_file`).
"""

import functools
import math
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from design_engine.calibration.fit import (CalibrationError, Fit, STIFFNESSES, check_fit_names,
                                           run_fit)
from design_engine.physics.energy import bond_geometry, make_energy
from design_engine.physics.geometry import block_geometry
from design_engine.physics.lattice import Lattice, periodic_design, quads
from design_engine.physics.linalg import implicit_point, spd_solve
from design_engine.physics.material import Material
from design_engine.physics.material_file import SI_UNITS
from design_engine.physics.regions import row_units

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
        qd = implicit_point(qs, lambda d, k: -spd_solve(h, grad_f(qs, d, k, loaded, sign)), d, k)
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
    names = check_fit_names(list(fit), STIFFNESSES, "hinge")
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


