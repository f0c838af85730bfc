"""CCSA-MMA (Svanberg 2002) with a sparse dual: the algorithm of NLopt's `LD_MMA`, made fast.

What: minimise f(x) subject to g_i(x) <= 0 (i < m) and optional bounds lower <= x <= upper by the
method of moving asymptotes in its globally convergent CCSA form (K. Svanberg, "A class of
globally convergent optimization methods based on conservative convex separable
approximations", SIAM J. Optim. 12 (2002) 555-573), making the choices NLopt makes in `LD_MMA`
(inner/outer iterations, rho and sigma updates, acceptance rule, stopping tests, evaluation
count), so that both evaluate the objective at the same sequence of points.

Why: every MMA step maximises a dual function of m variables (one per constraint). NLopt
evaluates that dual with dense O(m n) loops and maximises it with a nested MMA to 1e-14 relative
tolerance; for the design problem (n = 1616, m = 4448, <= ~16 nonzeros per Jacobian row) that
takes 40-100 s per outer step. Here the Jacobian is a scipy.sparse CSR matrix, so one dual
evaluation costs O(nnz + n + m), and the dual is maximised by a projected quasi-Newton method
preconditioned with the exact diagonal of its Hessian, warm-started from the previous
multipliers, to a KKT residual near roundoff. (scipy's L-BFGS-B was tried first: its bookkeeping
of the thousands of multipliers held at 0 costs 2-15 ms per call at m ~ 4000, so one solve took
0.5-1 s.) On random problems of that size with 10 nonzeros per row a dual solve takes
0.06-0.1 s and an outer step (3-4 evaluations) 0.25-0.3 s, besides the user's functions.

Validation (tests/test_mma.py): NLopt 2.11 (`LD_MMA`, initial step 1) and this module are run
on the same problems and the points at which they evaluate the objective are compared. Largest
differences: NLopt's tutorial problem (a bound, two active constraints) 4e-7 over 30
evaluations; a quadratic with four circle constraints 2e-8 (first 12), the same in a box 2e-7
(30; NLopt with dual_ftol_rel = 1e-16), with a fixed variable 9e-8 (30), from an infeasible start
7e-9 (first 14); an objective that is +inf beyond a wall 1e-8 (30, the same points hit it);
unconstrained Rosenbrock 2e-14 (40); a sparse problem with n = 200, m = 600 4e-6 (first 10).
The limit is NLopt's nested dual solve (ours reaches ~1e-12: it agrees to that with an exact
Newton solve of the dual): on the sparse problem NLopt's first step violates its own model
constraints by 2e-6 and differs by up to 4e-6 from NLopt run with a tighter dual tolerance.
Once rho has decayed to 1e-5 (after a dozen or so evaluations) the acceptance decisions turn on
differences at roundoff level, and the sequences part. The stopping tests (ftol, xtol, maximum
evaluations) stop both at the same evaluation.

Deviations from NLopt (only in cases NLopt handles badly):
- After an infeasible start, NLopt bounds the multipliers by 1e40, and where the model
  subproblem is infeasible they go to that bound. If the next point is feasible, the bound is
  lifted, and NLopt's nested dual solver, warm-started at y ~ 1e40 with a step of 1 (its default
  for unbounded variables), cannot bring them down: every later step ignores the objective and
  NLopt never improves on that point (tests/test_mma.py has a case). Here the dual is solved
  properly (from 0 if that is better), so the two part at that step.
- NaN from the objective is treated as +inf (NLopt leaves rho unchanged on NaN and so retries
  the same point until it runs out of evaluations). A trial with a non-finite objective is never
  accepted (NLopt accepts one while no feasible point is known if it lowers the infeasibility,
  which puts f = inf into the model).
- Non-finite constraint values raise ValueError (NLopt silently drops NaN constraints from the
  step). A non-finite objective at the start point, -inf anywhere, or a non-finite gradient where
  the objective is finite also raise ValueError.

Units: x in the caller's units; `initial_step` (sigma) in the same units: the initial distance
to the moving asymptotes (0.9 sigma is the move limit of a step).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.sparse as sp

__all__ = ["MMAOptions", "MMARecord", "MMAResult", "minimize"]

# Constants of NLopt's MMA (Svanberg's paper leaves them open).
_RHO_MIN = 1e-5  # lower limit of the penalty weights rho, rhoc (units of f resp. g)
_MOVE_LIMIT = 0.9  # a step has |dx_j| <= 0.9 sigma_j
_SIGMA_SHRINK, _SIGMA_GROW = 0.7, 1.2  # asymptote update after oscillating / monotone steps
_INFEASIBLE_DUAL_BOUND = 1e40  # upper bound of the multipliers while no feasible point is known

# Dual solver.
_DUAL_MAX_ITER = 5000  # iterations (it normally needs tens)
_DUAL_MEMORY = 10  # (s, y) pairs of the L-BFGS metric
_DUAL_STALL = 30  # give up after this many iterations without a smaller KKT residual

ObjectiveFn = Callable[[np.ndarray], tuple[float, np.ndarray]]
ConstraintFn = Callable[[np.ndarray], tuple[np.ndarray, "np.ndarray | sp.sparray | sp.spmatrix"]]


def _number(value) -> bool:
    return isinstance(value, int | float | np.integer | np.floating) and not isinstance(value, bool)


def _scalar_or_vector(name: str, value, positive: bool) -> float | np.ndarray:
    """A finite scalar or non-empty 1-D array, > 0 (positive) or >= 0; arrays are copied."""
    try:
        arr = np.array(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"MMAOptions.{name} must be a number or a 1-D array, "
                         f"got {value!r}") from None
    if arr.ndim > 1 or arr.size == 0:
        raise ValueError(f"MMAOptions.{name} must be a number or a non-empty 1-D array, "
                         f"got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"MMAOptions.{name} must be finite, got {value!r}")
    if not (np.all(arr > 0) if positive else np.all(arr >= 0)):
        raise ValueError(f"MMAOptions.{name} must be {'> 0' if positive else '>= 0'}, "
                         f"got {value!r}")
    if arr.ndim == 0:
        return float(arr)
    arr.setflags(write=False)
    return arr


def _bound(name: str, value, forbidden: float) -> np.ndarray | None:
    """A 1-D array of bounds without NaN or the infinity on the wrong side (copied)."""
    if value is None:
        return None
    arr = np.array(value, dtype=float)
    if arr.ndim != 1 or arr.size == 0:
        raise ValueError(f"MMAOptions.{name} must be a non-empty 1-D array, got shape {arr.shape}")
    if np.any(np.isnan(arr)) or np.any(arr == forbidden):
        raise ValueError(f"MMAOptions.{name} must not contain NaN or {forbidden}")
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True)
class MMAOptions:
    """Settings of `minimize` (NLopt's name in brackets).

    initial_step: sigma_0 > 0, a number or [n], units of x [set_initial_step]. (NLopt's default
        when it is not set: 1 for unbounded, (upper - lower) / 2 for bounded variables.)
    max_evals: stop once this many objective evaluations were made, >= 1 [set_maxeval].
    max_time_s: stop once this much wall time (s) has passed; > 0, inf = no limit [set_maxtime].
    ftol_rel: stop when an outer iteration changes f by less than ftol_rel |f|; 0 = off.
    xtol_rel: stop when an outer iteration moves x by less than xtol_rel |x| (1-norms); 0 = off.
    constraint_tol: a trial point counts as feasible if g(x) <= constraint_tol; >= 0, a number or
        [m], units of g [tol of add_inequality_mconstraint].
    dual_tol: each dual subproblem is solved until the residual of its optimality conditions,
        per constraint relative to |g_i| + sum_j |J_ij| sigma_j, is below this; in (0, 1e-3].
        1e-13 is near roundoff. Larger is faster (1e-6: about half the dual iterations), but
        each point then errs by about dual_tol * sigma (1e-6 gave 2e-6 to 2e-5 over 8 steps).
    lower, upper: bounds [n], default -inf / +inf [set_lower_bounds, set_upper_bounds].
    """

    initial_step: float | np.ndarray = 1.0
    max_evals: int = 100
    max_time_s: float = math.inf
    ftol_rel: float = 0.0
    xtol_rel: float = 0.0
    constraint_tol: float | np.ndarray = 1e-8
    dual_tol: float = 1e-13
    lower: np.ndarray | None = None
    upper: np.ndarray | None = None

    def __post_init__(self):
        put = object.__setattr__  # frozen: normalise the fields in place
        put(self, "initial_step", _scalar_or_vector("initial_step", self.initial_step, True))
        put(self, "constraint_tol",
            _scalar_or_vector("constraint_tol", self.constraint_tol, False))
        if not isinstance(self.max_evals, int | np.integer) or isinstance(self.max_evals, bool) \
                or self.max_evals < 1:
            raise ValueError(f"MMAOptions.max_evals must be an int >= 1, got {self.max_evals!r}")
        if not (_number(self.max_time_s) and self.max_time_s > 0):
            raise ValueError(f"MMAOptions.max_time_s must be > 0 (inf = no limit), "
                             f"got {self.max_time_s!r}")
        for name in ("ftol_rel", "xtol_rel"):
            value = getattr(self, name)
            if not (_number(value) and math.isfinite(value) and value >= 0):
                raise ValueError(f"MMAOptions.{name} must be finite and >= 0 (0 = off), "
                                 f"got {value!r}")
        if not (_number(self.dual_tol) and 0 < self.dual_tol <= 1e-3):
            raise ValueError(f"MMAOptions.dual_tol must be in (0, 1e-3], got {self.dual_tol!r}")
        put(self, "lower", _bound("lower", self.lower, math.inf))
        put(self, "upper", _bound("upper", self.upper, -math.inf))
        if self.lower is not None and self.upper is not None:
            if self.lower.shape != self.upper.shape:
                raise ValueError(f"MMAOptions.lower and upper differ in shape: "
                                 f"{self.lower.shape} vs {self.upper.shape}")
            if np.any(self.lower > self.upper):
                raise ValueError("MMAOptions.lower must be <= upper")


@dataclass(frozen=True)
class MMAResult:
    """Outcome of `minimize`.

    x: best accepted point [n] (NLopt's result); f: objective there; n_evals: objective
    evaluations made (the start point is the first); stop_reason: "max_evals", "max_time",
    "ftol" or "xtol"; n_outer: outer iterations begun (NLopt's k); feasible: g(x) <=
    constraint_tol; max_constraint: max_i g_i(x) (-inf if m = 0).
    """

    x: np.ndarray
    f: float
    n_evals: int
    stop_reason: str
    n_outer: int
    feasible: bool
    max_constraint: float


@dataclass(frozen=True)
class MMARecord:
    """One objective evaluation, passed to the optional callback of `minimize`.

    n_evals: evaluations so far, this one included; n_outer: its outer iteration (0 for the
    start point); x [n], f, max_constraint: the point, its objective and max_i g_i;
    accepted: it became the current point; conservative: the model was conservative there
    (this ends the inner loop); best_f: objective of the current point after this evaluation;
    rho: objective penalty weight of the model that proposed the point; dual_iters,
    dual_residual, dual_time_s: iterations, final KKT residual (see MMAOptions.dual_tol) and
    wall time (s) of the dual solve that proposed it.
    """

    n_evals: int
    n_outer: int
    x: np.ndarray
    f: float
    max_constraint: float
    accepted: bool
    conservative: bool
    best_f: float
    rho: float
    dual_iters: int
    dual_residual: float
    dual_time_s: float


@dataclass(eq=False)
class _Point:
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


class _SeparableModel:
    """Conservative convex separable approximation of f and g around an evaluated point x_k.

    For a step dx with |dx_j| < sigma_j (sigma_j: distance to the asymptotes, units of x_j):
        model of f:   f + sum_j (df_j sigma_j^2 dx_j + (|df_j| sigma_j + rho/2) dx_j^2)
                          / (sigma_j^2 - dx_j^2),
        model of g_i: the same with g_i, J_ij and rhoc_i in place of f, df_j and rho.
    Both are convex, separable and above the linearisation; rho, rhoc (units of f, g) make them
    more conservative. Steps are held to the bounds and to |dx_j| <= 0.9 sigma_j.
    Every method costs O(nnz + n + m) (sparse matrix-vector products).
    """

    def __init__(self, point: _Point, sigma: np.ndarray, rho: float, rhoc: np.ndarray,
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


# ----------------------------------------------------------------------------- dual solver


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


def _arc_search(model: _SeparableModel, y: np.ndarray, t: _Trial, g: np.ndarray,
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


def _maximise_dual(model: _SeparableModel, y0: np.ndarray, y_upper: float, tol: float,
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


def _solve_dual(model: _SeparableModel, y0: np.ndarray, y_upper: float, tol: float,
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
    if y0.max() > 1e-20 * _INFEASIBLE_DUAL_BOUND:
        zero = np.zeros_like(y0)
        if model.trial(zero).dual_change > model.trial(y0).dual_change:
            y0 = zero
    return _maximise_dual(model, y0, y_upper, tol, deadline)


# ----------------------------------------------------------------------------- driver


def _as_csr(jac, m: int, n: int) -> sp.csr_array:
    """Constraint Jacobian [m, n] (sparse or dense) as canonical CSR float64, checked finite."""
    if sp.issparse(jac):
        out = sp.csr_array(jac, dtype=float, copy=True)
    else:
        arr = np.asarray(jac, dtype=float)
        if arr.ndim == 1 and m == 1:
            arr = arr[None, :]
        out = sp.csr_array(arr)
    if out.shape != (m, n):
        raise ValueError(f"constraint Jacobian has shape {out.shape}, expected {(m, n)}")
    out.sum_duplicates()  # canonical: |J| must be taken entry by entry
    if not np.all(np.isfinite(out.data)):
        raise ValueError("constraint Jacobian contains non-finite values")
    return out


class _Evaluator:
    """Calls the user's functions, counts objective evaluations and checks what they return."""

    def __init__(self, fun: ObjectiveFn, constraints: ConstraintFn | None, n: int):
        self.fun, self.constraints, self.n = fun, constraints, n
        self.m: int | None = None if constraints is not None else 0
        self.n_evals = 0

    def __call__(self, x: np.ndarray) -> _Point:
        x = x.copy()
        x.setflags(write=False)
        f, df = self.fun(x)
        self.n_evals += 1
        f = float(f)
        if math.isnan(f):
            f = math.inf  # NaN means the same as +inf: never accepted, the next step is shorter
        if f == -math.inf:
            raise ValueError("objective returned -inf")
        if math.isfinite(f):
            df = np.array(df, dtype=float).reshape(-1)
            if df.shape != (self.n,):
                raise ValueError(f"objective gradient has shape {df.shape}, expected ({self.n},)")
            if not np.all(np.isfinite(df)):
                raise ValueError("objective gradient has non-finite entries where the "
                                 "objective is finite")
        else:
            df = np.zeros(self.n)  # unused: a point with f = +inf is never accepted
        if self.constraints is None:
            return _Point(x, f, df, np.zeros(0), sp.csr_array((0, self.n)))
        g, jac = self.constraints(x)
        g = np.array(g, dtype=float).reshape(-1)
        if self.m is None:
            self.m = g.size
        if g.shape != (self.m,):
            raise ValueError(f"constraints returned {g.size} values, expected {self.m}")
        if not np.all(np.isfinite(g)):
            bad = np.flatnonzero(~np.isfinite(g))
            raise ValueError(f"constraint values must be finite; got {g[bad[:5]].tolist()} "
                             f"at indices {bad[:5].tolist()} (of {bad.size} non-finite)")
        return _Point(x, f, df, g, _as_csr(jac, self.m, self.n))


def _per_entry(name: str, value, size: int) -> np.ndarray:
    """An option that is a number or an array, as a fresh float array [size]."""
    arr = np.asarray(value, dtype=float)
    if arr.ndim == 0:
        return np.full(size, float(arr))
    if arr.shape != (size,):
        raise ValueError(f"MMAOptions.{name} has {arr.size} entries, expected {size}")
    return arr.copy()


def _relstop(f_old: float, f_new: float, rel_tol: float) -> bool:
    """NLopt's relative-change test |f_new - f_old| < rel_tol (|f_new| + |f_old|) / 2."""
    if math.isinf(f_old):
        return False
    diff = abs(f_new - f_old)
    return diff < rel_tol * 0.5 * (abs(f_new) + abs(f_old)) or (rel_tol > 0 and f_new == f_old)


def minimize(fun: ObjectiveFn, constraints: ConstraintFn | None, x0, options: MMAOptions,
             callback: Callable[[MMARecord], None] | None = None) -> MMAResult:
    """Minimise fun(x) subject to constraints(x)[0] <= 0 and the bounds by CCSA-MMA.

    fun(x) -> (f, grad): objective (float) and its gradient [n]. f = +inf or NaN marks a point
        as unusable: it is never accepted and the next trial steps back towards the current point.
        x is passed read-only.
    constraints(x) -> (g, jac): values [m] (must be finite) and Jacobian [m, n], a scipy.sparse
        matrix or a dense array; None if there are no constraints.
    x0: start point [n], within the bounds; f(x0) must be finite. It is evaluation 1.
    options: MMAOptions. callback: called with an MMARecord after every evaluation.

    Each call of fun is one evaluation, as NLopt counts; constraints is called once after each.
    Exceptions raised by fun, constraints or callback propagate unchanged. The points are those
    NLopt's LD_MMA evaluates (to the accuracy of the dual solutions), and so are the evaluation
    count and the stopping decisions.
    """
    start = time.perf_counter()
    deadline = start + options.max_time_s
    x0 = np.array(x0, dtype=float).reshape(-1)
    n = x0.size
    if n == 0 or not np.all(np.isfinite(x0)):
        raise ValueError("x0 must be a non-empty finite vector")
    lower = _per_entry("lower", -math.inf if options.lower is None else options.lower, n)
    upper = _per_entry("upper", math.inf if options.upper is None else options.upper, n)
    if np.any(x0 < lower) or np.any(x0 > upper):
        raise ValueError("x0 is outside the bounds")
    sigma = _per_entry("initial_step", options.initial_step, n)
    bounded = np.isfinite(lower) & np.isfinite(upper)
    width = upper - lower

    evaluate = _Evaluator(fun, constraints, n)
    current = evaluate(x0)
    if not math.isfinite(current.f):
        raise ValueError("objective must be finite at x0")
    m = current.g.size
    tol = _per_entry("constraint_tol", options.constraint_tol, m)

    def report(point, n_outer, accepted, conservative, rho_used, dual):
        if callback is not None:
            iters, residual, seconds = dual
            callback(MMARecord(
                n_evals=evaluate.n_evals, n_outer=n_outer, x=point.x, f=point.f,
                max_constraint=point.max_constraint, accepted=accepted,
                conservative=conservative, best_f=current.f, rho=rho_used, dual_iters=iters,
                dual_residual=residual, dual_time_s=seconds))

    def stop_reason() -> str | None:
        if evaluate.n_evals >= options.max_evals:
            return "max_evals"
        if time.perf_counter() >= deadline:
            return "max_time"
        return None

    rho = 1.0
    rhoc = np.ones(m)
    y = np.zeros(m)  # dual variables, warm-started across all dual solves
    feasible = bool(np.all(current.g <= 0))
    infeasibility = max(0.0, current.max_constraint)
    y_upper = math.inf if feasible else _INFEASIBLE_DUAL_BOUND
    report(current, 0, True, True, rho, (0, 0.0, 0.0))

    # As in NLopt, the last *trial* point (accepted or not) and its objective drive the sigma
    # update and the ftol / xtol tests.
    x_trial, f_trial = current.x, current.f
    x_prev = x_prev2 = None
    k = 0
    reason = None
    while True:  # outer iterations
        reason = stop_reason()
        if reason is not None:
            break
        f_prev = f_trial
        k += 1
        x_prev2, x_prev = x_prev, x_trial

        while True:  # inner iterations: raise rho, rhoc until the model is conservative
            model = _SeparableModel(current, sigma, rho, rhoc, lower, upper)
            t0 = time.perf_counter()
            y, trial, iters, residual = _solve_dual(model, y, y_upper, options.dual_tol,
                                                    deadline)
            dual = (iters, residual, time.perf_counter() - t0)
            if time.perf_counter() >= deadline:
                reason = "max_time"
                break
            point = evaluate(trial.x)
            x_trial, f_trial = point.x, point.f
            conservative = trial.gval >= point.f and bool(np.all(trial.gcval >= point.g))
            feasible_trial = bool(np.all(point.g <= tol))
            infeasibility_trial = max(0.0, point.max_constraint)
            if math.isfinite(point.f) and (
                    (point.f < current.f and (conservative or feasible_trial or not feasible))
                    or (not feasible and infeasibility_trial < infeasibility)):
                current = point
                infeasibility = infeasibility_trial
                if infeasibility_trial == 0:
                    feasible = True
                    y_upper = math.inf
                report(point, k, True, conservative, rho, dual)
            else:
                report(point, k, False, conservative, rho, dual)
            reason = stop_reason()
            if reason is not None or conservative:
                break
            # Not conservative: raise the weights of the offending models. IEEE division as in
            # C (wval = 0 gives inf); f = +inf gives rho = 10 rho.
            with np.errstate(divide="ignore", invalid="ignore"):
                if point.f > trial.gval:
                    excess = np.float64(point.f - trial.gval) / np.float64(trial.wval)
                    rho = float(min(10.0 * rho, 1.1 * (rho + excess)))
                grow = point.g > trial.gcval
                excess_c = (point.g[grow] - trial.gcval[grow]) / np.float64(trial.wval)
                rhoc[grow] = np.minimum(10.0 * rhoc[grow], 1.1 * (rhoc[grow] + excess_c))
        if reason is not None:
            break

        if _relstop(f_prev, f_trial, options.ftol_rel):
            reason = "ftol"
        if np.abs(x_trial - x_prev).sum() < options.xtol_rel * np.abs(x_trial).sum():
            reason = "xtol"
        if reason is not None:
            break

        rho = max(0.1 * rho, _RHO_MIN)
        rhoc = np.maximum(0.1 * rhoc, _RHO_MIN)
        if k > 1:
            trend = (x_trial - x_prev) * (x_prev - x_prev2)
            sigma = sigma * np.where(trend < 0, _SIGMA_SHRINK,
                                     np.where(trend > 0, _SIGMA_GROW, 1.0))
            sigma[bounded] = np.clip(sigma[bounded], 0.01 * width[bounded],
                                     10.0 * width[bounded])

    return MMAResult(x=current.x.copy(), f=current.f, n_evals=evaluate.n_evals,
                     stop_reason=reason, n_outer=k, feasible=bool(np.all(current.g <= tol)),
                     max_constraint=current.max_constraint)
