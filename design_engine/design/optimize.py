"""The design loop (the one owner of nlopt): MMA on a task, recorded, checkpointed, resumable.

`run_design(task, out)` minimises -sign * objective (spec 9) under the vector constraints
(angles, edges: spec 3.2; the free vertices' angles, `constraints.free_vertex_constraints`;
tolerance 1e-8 per component) with exact JAX gradients and sparse
Jacobians, from the task's initial design with an initial move limit of 1 mm (spec 9.1).

Optimisers (`[optimizer] algorithm` of the task):
- `mma` (default): `design_engine.design.mma`, the CCSA-MMA scheme of NLopt's LD_MMA with its dual
  solved on the sparse constraint Jacobian; validated against NLopt iterate by iterate
  (`tests/test_mma.py`). NLopt's dual has one dense variable per constraint (4448 on 24x16) and
  took 40-100 s per evaluation there; ours takes a fraction of a second.
- `nlopt-mma`, `nlopt-ccsaq`: NLopt's LD_MMA / LD_CCSAQ (the paper's method), for comparison.

Every objective evaluation (MMA inner iterations included) is a record in `history.json`; a
failed evaluation (every solver failed, or a trial design with an inverted or self-intersecting
unit, which is not simulated) is fed back as +inf (MMA then shrinks its step) and recorded with
its reason; constraints are never NaN. After every evaluation the run folder holds what is needed to go on
(`checkpoint.npz`: every evaluated design with its objective value and gradient; `run.json`:
the resolved task). `resume=True` replays the record through a fresh optimiser from the same
start (values and gradients from the record, constraints recomputed), so the optimiser walks
the same sequence of designs as an uninterrupted run, and continues from where it stopped.
"""

import json
import logging
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from design_engine.design.constraints import make_sparse_constraints
from design_engine.design.evaluator import EvaluationFailed, TaskEvaluator
from design_engine.design.task import Task
from design_engine.physics.geometry import InvalidDesignError, check_design

log = logging.getLogger("metarig.design")

FEASIBLE_TOL = 1e-8  # max constraint of a feasible design (NLopt's tolerance, spec 3.2)
RUN_FORMAT = "metarig-design-run/1"


class ResumeError(RuntimeError):
    """A run folder that cannot be resumed with these settings; the message says why."""


class _Stop(Exception):
    """Raised inside the objective to end the run (budget spent)."""

    def __init__(self, reason: str):
        super().__init__(reason)
        self.reason = reason


@dataclass(frozen=True)
class DesignRun:
    """Outcome of `run_design`.

    Attributes:
        status: "complete" or "interrupted".
        stop_reason: "max_evals", "max_time", "ftol", "xtol", "interrupted".
        evaluations: the history records.
        best: index into `evaluations` of the best feasible one (None if none is feasible).
        best_x, last_x: [n_design] designs, mm.
        compilations: compiled value-and-gradient programs in this session.
    """

    status: str
    stop_reason: str
    evaluations: list[dict]
    best: int | None
    best_x: np.ndarray | None
    last_x: np.ndarray
    compilations: int


def _atomic_write(path: Path, data: bytes) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def _json_number(v):
    return v if v is None or math.isfinite(v) else None


def resumable(out: Path) -> bool:
    """Whether a design run folder holds a run to resume: its run.json and its checkpoint (a
    run killed between writing the two starts afresh)."""
    return (Path(out) / "run.json").exists() and (Path(out) / "checkpoint.npz").exists()


def read_record(out: Path) -> tuple[dict, dict, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """(run.json, history.json, (x, f, grad) of checkpoint.npz) of a run folder, read and
    checked without changing a byte of it.

    Raises:
        ResumeError: nothing to resume, or one line naming the damaged file and what to do.
    """
    from metarig.readback import DamagedFileError, damaged, read_json, read_npz

    out = Path(out)
    if not resumable(out):
        raise ResumeError(f"{out}: nothing to resume (no run.json and checkpoint.npz)")
    remedy = ("restore it from a copy to resume (the run's other files are left as they are), "
              "or start anew with another --out folder")
    try:
        run = read_json(out / "run.json", "design-run record", remedy)
        hist = read_json(out / "history.json", "design-run history", remedy)
        if not isinstance(hist.get("evaluations"), list):
            raise damaged(out / "history.json", "design-run history", "no list of evaluations",
                          remedy)
        ck = out / "checkpoint.npz"
        z = read_npz(ck, ("x", "f", "grad"), "design-run checkpoint", remedy)
        xs, fs, gs = z["x"], z["f"], z["grad"]
        if xs.ndim != 2 or fs.shape != xs.shape[:1] or gs.shape != xs.shape:
            raise damaged(ck, "design-run checkpoint", f"arrays of shapes x {xs.shape}, "
                          f"f {fs.shape}, grad {gs.shape} do not match", remedy)
    except DamagedFileError as exc:
        raise ResumeError(str(exc)) from None
    return run, hist, (xs, fs, gs)


class _Record:
    """The run's record on disk: history.json, checkpoint.npz, run.json (atomic writes)."""

    def __init__(self, out: Path, task: Task):
        self.out = out
        self.task = task
        self.evaluations: list[dict] = []
        self.x: list[np.ndarray] = []
        self.f: list[float] = []
        self.grad: list[np.ndarray] = []
        self.elapsed_before = 0.0

    def load(self) -> None:
        run, hist, (xs, fs, gs) = read_record(self.out)
        if run.get("format") != RUN_FORMAT or not isinstance(run.get("task"), dict):
            raise ResumeError(f"{self.out}/run.json is not a {RUN_FORMAT} file")
        if _settings(run["task"]) != _settings(self.task.document):
            raise ResumeError(f"{self.out} was started with other task settings; resume with "
                              "the same task and options, or use a new --out folder")
        n = min(len(hist["evaluations"]), xs.shape[0])
        if xs.shape[1:] != (self.task.free.size,):
            raise ResumeError(f"{self.out}: checkpoint has designs of size {xs.shape[1:]}")
        self.evaluations = hist["evaluations"][:n]
        self.x, self.f, self.grad = list(xs[:n]), [float(v) for v in fs[:n]], list(gs[:n])
        self.elapsed_before = float(run.get("elapsed_s", 0.0))

    def append(self, rec: dict, x, f, grad) -> None:
        self.evaluations.append(rec)
        self.x.append(np.array(x, np.float64))
        self.f.append(float(f))
        self.grad.append(np.array(grad, np.float64))

    def save(self, status: str, elapsed_s: float, extra: dict | None = None) -> None:
        import io

        buf = io.BytesIO()
        np.savez(buf, x=np.asarray(self.x).reshape(len(self.x), self.task.free.size),
                 f=np.asarray(self.f, np.float64),
                 grad=np.asarray(self.grad).reshape(len(self.x), self.task.free.size))
        _atomic_write(self.out / "checkpoint.npz", buf.getvalue())
        hist = {"task": self.task.name, "goal": self.task.goal,
                "terms": [t.name for t in self.task.terms], "evaluations": self.evaluations}
        _atomic_write(self.out / "history.json", json.dumps(hist, indent=1).encode())
        run = {"format": RUN_FORMAT, "task": _canonical(self.task.document), "status": status,
               "evaluations": len(self.evaluations), "elapsed_s": elapsed_s, **(extra or {})}
        _atomic_write(self.out / "run.json", json.dumps(run, indent=1).encode())


def _canonical(doc: dict) -> dict:
    return json.loads(json.dumps(doc, sort_keys=True))


def _settings(doc: dict) -> dict:
    """What fixes the sequence of designs: the task without its budget (a resumed run may be
    given more evaluations or time)."""
    return {k: v for k, v in _canonical(doc).items() if k != "budget"}


def best_feasible(evaluations: list[dict], goal: str) -> int | None:
    """Index of the best successful evaluation with max constraint <= 1e-8, or None."""
    sign = 1.0 if goal == "max" else -1.0
    best = None
    for i, e in enumerate(evaluations):
        if e["feasible"] and e["objective"] is not None:
            if best is None or sign * e["objective"] > sign * evaluations[best]["objective"]:
                best = i
    return best


def run_design(task: Task, out: Path, *, resume: bool = False, progress: bool = True,
               evaluator: TaskEvaluator | None = None,
               threads: int | None = None) -> DesignRun:
    """Optimise `task`, recording into folder `out` (see module docstring).

    Args:
        task: the resolved task.
        out: run folder (created); with `resume`, an earlier run of the same task.
        resume: continue the run recorded in `out`.
        progress: show a progress bar on stderr.
        evaluator: objective evaluator (default a new `TaskEvaluator(task, threads=threads)`,
            made once the run folder has been checked and closed when the run ends).
        threads: solves that may run at once (`TaskEvaluator`; default the usable cores).

    Raises:
        ResumeError: `out` cannot be resumed (or holds a run and `resume` is False).
        KeyboardInterrupt is caught: the run ends with status "interrupted" and its record kept.
    """
    out.mkdir(parents=True, exist_ok=True)
    record = _Record(out, task)
    if resume:
        record.load()
        log.info("resuming %s: %d evaluations on record (replayed without simulation)",
                 out, len(record.evaluations))
    elif resumable(out):  # (a checkpoint alone, a first save cut short, starts afresh)
        raise ResumeError(f"{out} already holds a design run; pass --resume to continue it or "
                          "choose another --out folder")
    own_evaluator = evaluator is None
    evaluator = evaluator or TaskEvaluator(task, threads=threads)
    free, x_base = task.free, task.initial_design
    constraints = make_sparse_constraints(task.lattice, task.limits, x_base, free)
    budget = task.budget
    session_start = time.perf_counter()
    state = {"last_end": time.perf_counter(), "cache": None, "calls": 0}
    bar = _progress_bar(task, progress, len(record.evaluations))

    def elapsed() -> float:
        return record.elapsed_before + time.perf_counter() - session_start

    def constraint_values(xf):
        c = state["cache"]
        if c is not None and np.array_equal(c[0], xf):
            return c[1], c[2]
        g, jac = constraints(xf)
        if not np.all(np.isfinite(g)):
            raise ValueError("non-finite constraint values (damaged design)")
        state["cache"] = (np.array(xf, np.float64), g, jac)
        return g, jac

    def fun(xf):
        xf = np.array(xf, np.float64)  # a copy: NLopt hands over a view of its own buffer
        i = state["calls"]
        state["calls"] += 1
        if i < len(record.x):  # replay: the optimiser must ask for the recorded design
            if not np.allclose(xf, record.x[i], rtol=0.0, atol=1e-9):
                raise ResumeError(f"cannot resume: evaluation {i + 1} asks for a design that "
                                  "differs from the record (other optimiser settings or "
                                  "software version?)")
            state["last_end"] = time.perf_counter()
            return record.f[i], record.grad[i]
        if i >= budget.max_evals:
            raise _Stop("max_evals")
        if elapsed() >= budget.max_time_s:
            raise _Stop("max_time")
        opt_s = time.perf_counter() - state["last_end"]
        x = task.embed(xf)
        t0 = time.perf_counter()
        event, terms, solver, unused = None, None, None, 0
        try:
            # a trial may leave the constraint set; a unit that is inverted or self-intersecting
            # (beyond a constraint's bound: a free corner closed past 0) is no design
            check_design(task.lattice, x)
            ev = evaluator.evaluate(x)
            f, grad = -task.sign * ev.value, -task.sign * ev.grad[free]
            terms, solver, sim_s, unused = ev.terms, ev.solver, ev.sim_s, ev.ahead_unused
            if ev.events:
                event = "; ".join(ev.events)
        except EvaluationFailed as exc:
            f, grad, sim_s = math.inf, np.zeros(free.size), time.perf_counter() - t0
            event = f"evaluation failed: {exc}"
        except InvalidDesignError as exc:
            f, grad, sim_s = math.inf, np.zeros(free.size), time.perf_counter() - t0
            event = f"invalid geometry, not simulated: {exc}"
        t1 = time.perf_counter()
        g, _ = constraint_values(xf)
        jac_s = time.perf_counter() - t1
        max_g = float(np.max(g))
        rec = {
            "eval": i + 1,
            "objective": None if terms is None else _json_number(task.scalarised_si(terms)),
            "objectives": None if terms is None else task.objectives_si(terms),
            "max_constraint": max_g,
            "feasible": bool(max_g <= FEASIBLE_TOL),
            "wall_s": time.perf_counter() - t0 + opt_s,
            "event": event,
            "failed": terms is None,
            "sim_s": sim_s, "jac_s": jac_s, "opt_s": opt_s, "ahead_unused": unused,
            "optimiser_value": _json_number(f),
            "metrics": {} if terms is None else task.metrics(terms),
            "solver": solver,
        }
        record.append(rec, xf, f, grad)
        record.save("running", elapsed(), {"compilations": evaluator.compilations})
        if bar is not None:
            bar.update(1)
            bar.set_postfix_str(_postfix(rec))
        if event:
            log.info("evaluation %d: %s", i + 1, event)
        state["last_end"] = time.perf_counter()
        return f, grad

    x0 = x_base[free]
    status, reason = "complete", "max_evals"
    try:
        reason = _minimise(task, fun, constraint_values, x0, budget.max_evals)
    except _Stop as stop:
        reason = stop.reason
    except KeyboardInterrupt:
        status, reason = "interrupted", "interrupted"
    finally:
        if bar is not None:
            bar.close()
        if own_evaluator:
            evaluator.close()
    record.save(status, elapsed(), {"compilations": evaluator.compilations,
                                    "stop_reason": reason})
    evals = record.evaluations
    best = best_feasible(evals, task.goal)

    return DesignRun(status=status, stop_reason=reason, evaluations=evals, best=best,
                     best_x=None if best is None else task.embed(record.x[best]),
                     last_x=task.embed(record.x[-1]) if evals else x_base.copy(),
                     compilations=evaluator.compilations)


def _minimise(task: Task, fun, constraint_values, x0: np.ndarray, max_evals: int) -> str:
    """Run the task's optimiser to its budget; returns the stop reason."""
    opt = task.optimizer
    if opt.algorithm == "mma":
        from design_engine.design.mma import MMAOptions, minimize

        res = minimize(fun, constraint_values, x0,
                       MMAOptions(initial_step=opt.initial_step_mm, max_evals=max_evals,
                                  ftol_rel=task.budget.ftol_rel, constraint_tol=FEASIBLE_TOL))
        return res.stop_reason
    import nlopt

    algo = nlopt.LD_MMA if opt.algorithm == "nlopt-mma" else nlopt.LD_CCSAQ
    n = x0.size
    nl = nlopt.opt(algo, n)

    def objective(x, grad):
        f, g = fun(x)
        if grad.size:
            grad[:] = g
        return float(f)

    def both(result, x, grad):
        g, jac = constraint_values(np.asarray(x))
        result[:] = g
        if grad.size:
            grad[:, :] = jac.toarray()

    m = constraint_values(x0)[0].size
    nl.set_min_objective(objective)
    nl.add_inequality_mconstraint(both, [FEASIBLE_TOL] * m)
    nl.set_initial_step(opt.initial_step_mm)
    nl.set_maxeval(max_evals)
    if task.budget.ftol_rel > 0:
        nl.set_ftol_rel(task.budget.ftol_rel)
    if opt.nlopt_dual_ftol_rel is not None:
        nl.set_param("dual_ftol_rel", opt.nlopt_dual_ftol_rel)
    nl.optimize(x0)
    return {nlopt.MAXEVAL_REACHED: "max_evals", nlopt.FTOL_REACHED: "ftol",
            nlopt.XTOL_REACHED: "xtol", nlopt.MAXTIME_REACHED: "max_time"}.get(
        nl.last_optimize_result(), f"nlopt result {nl.last_optimize_result()}")


def _postfix(rec: dict) -> str:
    obj = "failed" if rec["objective"] is None else f"{rec['objective']:.4g}"
    return (f"obj {obj}, max g {rec['max_constraint']:.2g}, {rec['wall_s']:.2f} s/eval")


def _progress_bar(task: Task, enabled: bool, done: int):
    if not enabled:
        return None
    from tqdm import tqdm

    return tqdm(total=task.budget.max_evals, initial=done, desc=f"design {task.name}",
                unit="eval", dynamic_ncols=True)


__all__ = ["FEASIBLE_TOL", "DesignRun", "ResumeError", "best_feasible", "read_record",
           "run_design"]
