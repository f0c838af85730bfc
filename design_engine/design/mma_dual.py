"""The CCSA model of one MMA step and its dual solver (`mma.minimize` drives them).

`SeparableModel` is Svanberg's conservative convex separable approximation of the objective and
the constraints around an evaluated `Point`; `solve_dual` maximises its dual over the m
multipliers by a projected quasi-Newton method preconditioned with the exact diagonal of the
dual's Hessian, warm-started from the previous multipliers, to a KKT residual near roundoff.
Every model evaluation costs O(nnz + n + m) (sparse matrix-vector products). See `mma` for the
method, its validation against NLopt and the deviations.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.sparse as sp

_MOVE_LIMIT = 0.9  # a step has |dx_j| <= 0.9 sigma_j (NLopt's constant)
INFEASIBLE_DUAL_BOUND = 1e40  # upper bound of the multipliers while no feasible point is known
_DUAL_MAX_ITER = 5000  # iterations (it normally needs tens)
_DUAL_MEMORY = 10  # (s, y) pairs of the L-BFGS metric
_DUAL_STALL = 30  # give up after this many iterations without a smaller KKT residual


@dataclass(eq=False)
class Point:
    """An evaluated point: x [n], f, df = grad f [n], g [m], jac = dg/dx (CSR [m, n]).

    The forms of the Jacobian that the dual needs are built once per point, on first use.
    """

    x: np.ndarray
    f: float
    df: np.ndarray
    g: np.ndarray
    jac: sp.csr_array

    @property
    def max_constraint(self) -> float:
        return float(self.g.max()) if self.g.size else -math.inf

    def _same_pattern(self, data: np.ndarray) -> sp.csr_array:
        return sp.csr_array((data, self.jac.indices, self.jac.indptr), shape=self.jac.shape)

    @cached_property
    def abs_jac(self) -> sp.csr_array:
        return self._same_pattern(np.abs(self.jac.data))

    @cached_property
    def jac_t(self) -> sp.csr_array:
        return self.jac.T.tocsr()

    @cached_property
    def abs_jac_t(self) -> sp.csr_array:
        return self.abs_jac.T.tocsr()

    @cached_property
    def jac_sq(self) -> sp.csr_array:
        """J_ij^2 (= |J_ij|^2)."""
        return self._same_pattern(self.jac.data * self.jac.data)

    @cached_property
    def jac_signed_sq(self) -> sp.csr_array:
        """J_ij |J_ij|."""
        return self._same_pattern(self.jac.data * np.abs(self.jac.data))


@dataclass
class _Trial:
    """The minimiser of the model Lagrangian for given multipliers y, and the model there.

    x: trial point [n]; dx = x - x_k [n]; dual_change: dual value - f (units of f; summed
    without f, so its rounding error is that of the change) and dual_roundoff, a bound on that
    error; gval: model objective at x; gcval: model constraints at x [m] (= gradient of the
    dual w.r.t. y); wval: sum_j dx_j^2 / (2 (sigma_j^2 - dx_j^2)) (dimensionless, the weight
    of rho in the model); u, v [n]: coefficients of the Lagrangian (see `trial`).
    """

    x: np.ndarray
    dx: np.ndarray
    dual_change: float
    dual_roundoff: float
    gval: float
    wval: float
    gcval: np.ndarray
    u: np.ndarray
    v: np.ndarray


class SeparableModel:
    """Conservative convex separable approximation of f and g around an evaluated point x_k.

    For a step dx with |dx_j| < sigma_j (sigma_j: distance to the asymptotes, units of x_j):
        model of f:   f + sum_j (df_j sigma_j^2 dx_j + (|df_j| sigma_j + rho/2) dx_j^2)
                          / (sigma_j^2 - dx_j^2),
        model of g_i: the same with g_i, J_ij and rhoc_i in place of f, df_j and rho.
    Both are convex, separable and above the linearisation; rho, rhoc (units of f, g) make them
    more conservative. Steps are held to the bounds and to |dx_j| <= 0.9 sigma_j.
    Every method costs O(nnz + n + m) (sparse matrix-vector products).
    """

    def __init__(self, point: Point, sigma: np.ndarray, rho: float, rhoc: np.ndarray,
                 lower: np.ndarray, upper: np.ndarray):
        self.point = point
        self.sigma, self.rho, self.rhoc = sigma, rho, rhoc
        self.sigma2 = sigma * sigma
        self.fixed = sigma == 0  # coordinates without room to move (lower == upper)
        self.any_fixed = bool(np.any(self.fixed))
        self.v_f = np.abs(point.df) * sigma + 0.5 * rho  # objective part of v [n]
        self.step_lo = np.maximum(lower, point.x - _MOVE_LIMIT * sigma)
        self.step_hi = np.minimum(upper, point.x + _MOVE_LIMIT * sigma)
        if self.any_fixed:
            self.step_lo[self.fixed] = point.x[self.fixed]
            self.step_hi[self.fixed] = point.x[self.fixed]
        # |g_i| + sum_j |J_ij| sigma_j [m] (units of g, > 0): the size of the terms of g~_i
        self.row_scale = np.maximum(np.abs(point.g) + point.abs_jac @ sigma, 1e-300)

    def trial(self, y: np.ndarray) -> _Trial:
        """Minimise the model Lagrangian f~ + y . g~ over the step box for multipliers y >= 0.

        Per coordinate the Lagrangian is (u dx + v dx^2) / (sigma^2 - dx^2) (plus constants)
        with u = sigma^2 (df + J^T y) and v = |df| sigma + rho/2 + sigma |J|^T y + (rhoc . y)/2.
        """
        p, sigma, sigma2 = self.point, self.sigma, self.sigma2
        u = (p.df + p.jac_t @ y) * sigma2
        v = self.v_f + sigma * (p.abs_jac_t @ y) + 0.5 * float(self.rhoc @ y)  # > 0
        with np.errstate(invalid="ignore", divide="ignore"):
            ratio = u / v
            # the root of  u dx^2 + 2 v sigma^2 dx + u sigma^2 = 0  with |dx| < sigma, in the
            # form without cancellation as u -> 0 (|u / (v sigma)| <= 1 by construction)
            dx = ratio / (-1.0 - np.sqrt(np.abs(1.0 - (ratio / sigma) ** 2)))
        if self.any_fixed:
            dx[self.fixed] = 0.0
        x_new = np.minimum(np.maximum(p.x + dx, self.step_lo), self.step_hi)
        dx = x_new - p.x
        dx2 = dx * dx
        if self.any_fixed:
            den_inv = np.zeros_like(dx)
            np.divide(1.0, sigma2 - dx2, out=den_inv, where=~self.fixed)
            u = np.where(self.fixed, 0.0, u)
        else:
            den_inv = 1.0 / (sigma2 - dx2)
        phi = dx2 * den_inv  # dx^2 / (sigma^2 - dx^2)
        lin = sigma2 * dx * den_inv  # sigma^2 dx / (sigma^2 - dx^2)
        sum_phi = float(phi.sum())
        terms = y * p.g
        lag = u * (dx * den_inv) + v * phi
        dual_change = float(terms.sum()) + float(lag.sum())
        roundoff = 8.0 * np.finfo(float).eps * (float(np.abs(terms).sum())
                                                + float(np.abs(lag).sum()))
        gval = p.f + float(p.df @ lin + self.v_f @ phi)
        gcval = p.g + p.jac @ lin + p.abs_jac @ (sigma * phi) + 0.5 * self.rhoc * sum_phi
        return _Trial(x=x_new, dx=dx, dual_change=dual_change, dual_roundoff=roundoff,
                      gval=gval, wval=0.5 * sum_phi, gcval=gcval, u=u, v=v)

    def hessian_diagonal(self, t: _Trial) -> np.ndarray:
        """Diagonal of -(d^2 dual / d y^2) at a trial point [m] (> 0).

        With A_ij = d g~_i / d x_j and D_j = d^2 L / d x_j^2 over the coordinates not held at
        the edge of the step box, the dual's Hessian is -A D^-1 A^T. A = S + rhoc w^T: S has
        the pattern of J (S_ij = J_ij a_j + |J_ij| b_j), the rank-one part comes from the rhoc
        terms, which involve every coordinate. So the diagonal takes four sparse products.
        """
        p, sigma, sigma2, dx = self.point, self.sigma, self.sigma2, t.dx
        free = (t.x > self.step_lo) & (t.x < self.step_hi)
        q = np.where(free, (sigma2 - dx * dx) ** 2, 1.0)
        with np.errstate(divide="ignore", invalid="ignore"):
            lag2 = 2.0 * (t.u * dx + t.v * sigma2) / q  # D_j
            inv = np.where(free & (lag2 > 0), 1.0 / lag2, 0.0)
        a = sigma2 * (sigma2 + dx * dx) / q  # d lin / d dx
        b = 2.0 * sigma2 * sigma * dx / q  # d (sigma phi) / d dx
        w = sigma2 * dx / q  # d (phi / 2) / d dx
        r = self.rhoc
        h = (p.jac_sq @ ((a * a + b * b) * inv) + p.jac_signed_sq @ (2.0 * a * b * inv)
             + 2.0 * r * (p.jac @ (a * w * inv) + p.abs_jac @ (b * w * inv))
             + r * r * float(w @ (w * inv)))
        h_max = float(h.max(initial=0.0))
        return np.maximum(h, 1e-12 * h_max if h_max > 0 else 1.0)

    def kkt_residual(self, y: np.ndarray, t: _Trial, y_upper: float) -> float:
        """max_i |projected dual gradient_i| / row_scale_i (dimensionless; 0 at the optimum)."""
        pg = np.where((y <= 0) & (t.gcval < 0), 0.0, t.gcval)
        pg = np.where((y >= y_upper) & (pg > 0), 0.0, pg)
        return float(np.max(np.abs(pg) / self.row_scale, initial=0.0))




def _lbfgs_direction(q: np.ndarray, free: np.ndarray, h: np.ndarray,
                     memory: list) -> np.ndarray:
    """H q on the free components [m] (0 elsewhere), H the L-BFGS inverse-Hessian estimate.

    The stored pairs (s, y) are restricted to the free components, the initial matrix is
    diag(1 / h); pairs without positive curvature there are skipped.
    """
    q = np.where(free, q, 0.0)
    pairs = []
    for s, yv in memory:
        s_f, y_f = np.where(free, s, 0.0), np.where(free, yv, 0.0)
        sy = float(s_f @ y_f)
        if sy > 1e-12 * math.sqrt(float(s_f @ s_f) * float(y_f @ y_f)):
            pairs.append((s_f, y_f, 1.0 / sy))
    coefs = []
    for s, yv, rho in reversed(pairs):
        a = rho * float(s @ q)
        q -= a * yv
        coefs.append(a)
    r = q / h
    for (s, yv, rho), a in zip(pairs, reversed(coefs), strict=True):
        r += s * (a - rho * float(yv @ r))
    return r


def _arc_search(model: SeparableModel, y: np.ndarray, t: _Trial, g: np.ndarray,
                d: np.ndarray, y_upper: float) -> tuple[np.ndarray, _Trial] | None:
    """Search y(alpha) = clip(y + alpha d, 0, y_upper) for a lower -(dual - f) (Armijo, 1e-4).

    g: gradient of -(dual - f) at y. Starts at alpha = 1 and halves. If the full step is taken
    while the slope along d is still >= 90 % of the initial one (the dual rises about linearly,
    as when the model subproblem is infeasible and the multipliers must reach their bound),
    alpha grows 10x while that lasts. A decrease within rounding error counts (near the optimum
    the dual is flat to roundoff; the gradient, which is accurate, keeps steering).
    Returns (y, trial) or None if no step is accepted.
    """
    phi = -t.dual_change
    slope = float(g @ d)

    def attempt(alpha):
        y_a = np.clip(y + alpha * d, 0.0, y_upper)
        if np.array_equal(y_a, y) or not np.all(np.isfinite(y_a)):
            return None
        t_a = model.trial(y_a)
        if not math.isfinite(t_a.dual_change):
            return None  # (an unbounded dual: only if the model subproblem is infeasible)
        allowance = t.dual_roundoff + t_a.dual_roundoff
        if -t_a.dual_change <= phi + 1e-4 * float(g @ (y_a - y)) + allowance:
            return y_a, t_a
        return None

    alpha = 1.0
    found = attempt(alpha)
    while found is None and alpha > 1e-12:
        alpha *= 0.5
        found = attempt(alpha)
    if found is None or alpha < 1.0 or not slope < 0:
        return found
    for _ in range(40):
        if float(-found[1].gcval @ d) > 0.9 * slope:
            break  # the slope has flattened: long enough
        alpha *= 10.0
        longer = attempt(alpha)
        if longer is None or np.array_equal(longer[0], found[0]):
            break
        found = longer
    return found


def _maximise_dual(model: SeparableModel, y0: np.ndarray, y_upper: float, tol: float,
                   deadline: float) -> tuple[np.ndarray, _Trial, int, float]:
    """Maximise the dual over 0 <= y <= y_upper from y0 [m] by projected quasi-Newton.

    The two-metric projection method (Bertsekas 1982) with an L-BFGS metric (as in Kim, Sra &
    Dhillon 2010) whose initial matrix is the exact diagonal of the dual's Hessian: multipliers
    that a diagonal Newton step would push through a bound are moved onto it, the others take
    an L-BFGS step, restricted to them; a search along the projection arc follows.
    Stops when model.kkt_residual <= tol, after _DUAL_STALL iterations without progress, or at
    the deadline (time.perf_counter() value). Returns (y, trial, iterations, residual) for the
    iterate with the smallest residual.
    """
    y = np.clip(y0, 0.0, y_upper)
    t = model.trial(y)
    memory: list = []
    best = (math.inf, y, t)
    since_best = 0
    it = 0
    for it in range(_DUAL_MAX_ITER):  # noqa: B007 (the count is returned)
        res = model.kkt_residual(y, t, y_upper)
        if res < best[0]:
            best, since_best = (res, y, t), 0
        else:
            since_best += 1
        if res <= tol or since_best > _DUAL_STALL or time.perf_counter() > deadline:
            break
        g = -t.gcval  # gradient of the minimised -(dual - f)
        h = model.hessian_diagonal(t)
        diag_step = g / h
        held = ((g > 0) & (y - diag_step <= 0)) | ((g < 0) & (y - diag_step >= y_upper))
        d = -_lbfgs_direction(g, ~held, h, memory)
        d[held] = -diag_step[held]
        if not float(g[~held] @ d[~held]) < 0:  # no descent: fall back to the diagonal step
            memory.clear()
            d = -diag_step
        step = _arc_search(model, y, t, g, d, y_upper)
        if step is None:
            if not memory:
                break
            memory.clear()
            continue
        y_new, t_new = step
        memory.append((y_new - y, t.gcval - t_new.gcval))  # (s, change of the gradient)
        if len(memory) > _DUAL_MEMORY:
            memory.pop(0)
        y, t = y_new, t_new
    return best[1], best[2], it, best[0]


def solve_dual(model: SeparableModel, y0: np.ndarray, y_upper: float, tol: float,
                deadline: float) -> tuple[np.ndarray, _Trial, int, float]:
    """Maximise the dual over 0 <= y <= y_upper from the warm start y0 [m].

    While no feasible point is known, y_upper = 1e40 (as NLopt). If the model subproblem has
    no feasible point, the dual rises without limit until the multipliers reach that bound, and
    the step minimises a weighted sum of the model constraints. When the warm start is of that
    kind (max y0 > 1e20), the solve starts from whichever of it and 0 has the larger dual.
    (NLopt's nested dual solver cannot leave such a warm start once the bound is lifted: it
    moves the multipliers by < 1 per iteration. See the module docstring.)
    Returns (y [m], trial at y, iterations, KKT residual).
    """
    if y0.size == 0:
        return y0, model.trial(y0), 0, 0.0
    if y0.max() > 1e-20 * INFEASIBLE_DUAL_BOUND:
        zero = np.zeros_like(y0)
        if model.trial(zero).dual_change > model.trial(y0).dual_change:
            y0 = zero
    return _maximise_dual(model, y0, y_upper, tol, deadline)
