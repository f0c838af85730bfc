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

import numpy as np
import scipy.sparse as sp

from design_engine.design.mma_dual import INFEASIBLE_DUAL_BOUND, Point, SeparableModel, solve_dual

__all__ = ["MMAOptions", "MMARecord", "MMAResult", "minimize"]

# Constants of NLopt's MMA (Svanberg's paper leaves them open).
_RHO_MIN = 1e-5  # lower limit of the penalty weights rho, rhoc (units of f resp. g)
_SIGMA_SHRINK, _SIGMA_GROW = 0.7, 1.2  # asymptote update after oscillating / monotone steps

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

    def __call__(self, x: np.ndarray) -> Point:
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
            return Point(x, f, df, np.zeros(0), sp.csr_array((0, self.n)))
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
        return Point(x, f, df, g, _as_csr(jac, self.m, self.n))


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
    y_upper = math.inf if feasible else INFEASIBLE_DUAL_BOUND
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
            model = SeparableModel(current, sigma, rho, rhoc, lower, upper)
            t0 = time.perf_counter()
            y, trial, iters, residual = solve_dual(model, y, y_upper, options.dual_tol,
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
