"""A task's objective as the optimiser sees it: value and exact gradient for any design.

One compiled value-and-gradient per solver configuration (the design, material, loading, sample
times and weights are traced arguments, so every evaluation, every scene of the same topology and
every run of a sweep in the same process reuses it). Per evaluation and scene the solver policy (`solve.policy`) applies, with two additions
that an optimisation needs:
- the fixed step is kept valid while the design changes: before each fixed-step solve the
  highest natural frequency of the *current* design is re-measured at the state its solve
  starts from (rest, or this design's own static pre-compression, solved once before the solve
  and handed to it as its start state, the solve's gradient pulled back through the
  equilibrium by a program of its own, `run.static_start`) (a warm-started
  power iteration, `STEP_CHECK_ITERATIONS` Hessian-vector products, a few per cent of a solve)
  and
  when the step exceeds `STEP_RECHECK` x the scheme's stability limit (`policy.stability_limit`:
  2/omega_max, or 2.72/omega_max for the fourth order of a static pre-compression in contact,
  whose step is STATIC_CONTACT_STEP x Verlet's) a new step is taken (`policy.fixed_step`:
  `policy.STABILITY_SAFETY` x 2/omega_max x that multiple; one more
  compilation, recorded as an event), or, when that step would
  be below `MIN_STEP_FRACTION` of the first one (the contact barrier of a design pressed deep
  into contact sets the frequency), adaptive Dopri8 from then on; a solve that still goes
  non-finite is caught and redone with the fallback configuration;
- a design whose voids reach the contact cutoff is re-solved as `policy.next_config` says (with
  contact at the same step; once at half the step, or with Dopri8, when the barrier outgrows it
  or the work-energy balance drifts), and a failed solve is retried with the fallback; if that
  fails too the evaluation raises `EvaluationFailed`;
- every adaptive solve has the task's step budget (`budget.max_solve_steps`): one that uses it
  up raises `EvaluationFailed` at once, with no fallback (a slower solver would grind on the same
  near-singular contact), so the optimiser records a failed design and steps back instead of
  spending an hour on it.
Every such step is recorded with its reason.

XLA runs each dynamic solve on one core; the static solver's factorisations use every core
that is free. With `threads` above 1 (the default: the cores this process may use) an
evaluation solves its scenes' static equilibria first, one after the other
(`_equilibria_first`), then its scenes side by side, and a scene's check starts beside its
step (`driver.solve_with_policy(ahead=)`); the results, events and records are the same as
on one thread. A Dask worker of a sweep, whose neighbours already fill
the cores, evaluates on one (`threads=1`).
"""

import dataclasses
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from design_engine.design.task import OPTIMISER_SCALE, Task
from design_engine.design.task_schema import Term
from design_engine.solve.driver import PolicyFailed, solve_with_policy
from design_engine.solve.fixed_step import is_fixed_step
from design_engine.solve.objectives import objective_term
from design_engine.solve.policy import (choose_config, contact_config, fixed_step,
                                        for_gradient, initial_vector, make_frequency_estimator,
                                        stability_limit, step_reason)
from design_engine.solve.run import (cached_program, checked, compile_key, config_summary,
                                     prestressed_state, split_gradient, static_equilibrium,
                                     static_start)
from design_engine.solve.simulate import (SimulationError, Solution, SolverConfig, make_simulator,
                                          solve_health)
from metarig.cores import usable_cores

STEP_RECHECK = 0.8  # re-choose the fixed step above this fraction of the stability limit
STEP_CHECK_ITERATIONS = 30  # warm-started power iterations per evaluation
MIN_STEP_FRACTION = 0.25  # below this fraction of the first fixed step, use the adaptive solver
INITIAL_ITERATIONS = 300  # cold power iterations for the initial design


def term_value(term: Term, sol: Solution, ids, point=None):
    """Internal value of one objective term on a solution (`objectives.objective_term`)."""
    return objective_term(term.quantity, sol, ids, point)


def task_terms(task: Task, solutions: dict[str, Solution]) -> dict[str, float]:
    """Term name -> internal value, from one solution per scene (scene name -> Solution)."""
    return {t.name: float(term_value(t, solutions[t.scene], task.targets[t.target],
                                     task.spin_point)) for t in task.terms}


class EvaluationFailed(RuntimeError):
    """Every configuration failed for this design; the message says why. `state` is the scene's
    state to keep (its step check stands)."""

    def __init__(self, message: str, state=None):
        super().__init__(message)
        self.state = state


@dataclass(frozen=True)
class Evaluation:
    """One evaluated design.

    Attributes:
        value: scalarised objective in optimiser units (sum_i w_i * scale_i * term_i).
        grad: [n_design] d value / d x, per mm.
        terms: term name -> internal value (J_Omega mJ summed over samples, or J_L g mm^2/ms).
        solver: scene name -> {"config": summary, "why": [reasons]} of the solve that counted.
        events: what happened beyond the plain solve (step re-chosen, contact, fallback).
        sim_s: wall time of the solves and step checks, s.
        ahead_unused: half-step solves started ahead on another thread (`threads` > 1) that
            ran and were not asked for, over the scenes (`driver.Outcome.unused_ahead`).
    """

    value: float
    grad: np.ndarray
    terms: dict[str, float]
    solver: dict[str, dict]
    events: tuple[str, ...] = field(default=())
    sim_s: float = 0.0
    ahead_unused: int = 0


@dataclass(frozen=True)
class SceneState:
    """What the evaluator carries for one scene from one evaluation to the next; each
    evaluation returns a new one (`dataclasses.replace`)."""

    config: SolverConfig
    reasons: tuple[str, ...]
    omega: float | None = None
    vector: np.ndarray | None = None
    last_config: SolverConfig | None = None  # the configuration the last evaluation ended with
    first_dt: float = 0.0  # the first fixed step chosen, ms
    last_health: dict | None = None


class _ScenePrograms(NamedTuple):
    """A scene's programs under one configuration (`TaskEvaluator._function`)."""

    forward: object  # (x, material, loading, ts, weights, initial, equilibrium) -> (J, aux, pb)
    reverse: object  # (pullback, seed) -> gradient in x
    objective: object  # the objective, not compiled
    forward_from_start: object  # ((x, q_s), material, loading, ts, weights) -> (J, aux, pb)
    reverse_from_start: object  # (pullback, seed) -> (gradient in x, cotangent on q_s)


@dataclass(frozen=True)
class _SceneOutcome:
    """One scene's share of an evaluation (`TaskEvaluator._solve_scene`)."""

    value: float
    grad: np.ndarray
    terms: dict[str, float]
    record: dict  # the configuration that counted, and why
    events: list[str]
    state: SceneState  # the scene's state for the next evaluation
    ahead_unused: int  # half-step solves started ahead that went unused


class TaskEvaluator:
    """Evaluates a task's scalarised objective and its gradient (see module docstring)."""

    def __init__(self, task: Task, config: SolverConfig | None = None,
                 threads: int | None = None):
        """`config` forces one configuration on every scene, with no policy (no step checks,
        no re-solves, no fallback, its own step budget): for comparisons against a fixed
        method. `threads`: how many solves may run at once (default: the cores this process
        may use; 1 solves one after the other)."""
        self.task = task
        self.forced = config
        threads = usable_cores() if threads is None else threads
        if threads < 1:
            raise ValueError(f"threads must be at least 1, got {threads}")
        # scenes side by side, and each scene's half-step solve started ahead on a pool of its
        # own (a scene waits on that pool, never the other way round)
        self._scenes = ThreadPoolExecutor(threads, "metarig-scene") if threads > 1 else None
        self._ahead = ThreadPoolExecutor(threads, "metarig-ahead") if threads > 1 else None
        self.max_solve_steps = task.budget.max_solve_steps
        self.compilations = 0
        self._estimators: dict[str, object] = {}
        self._state: dict[str, SceneState] = {}
        for name, scene in task.scenes.items():
            if config is not None:
                self._state[name] = SceneState(config, ("configuration given by the caller",))
                continue
            omega, vec, state = None, None, None
            if scene.loading.strain == 0.0 or scene.loading.is_static:
                if self._static(name):  # the static equilibrium the pulse starts from
                    state = self._equilibrium(name, task.initial_design)
                omega, vec = self._frequency(name, task.initial_design, None, state)
            choice = choose_config(scene, omega=omega, state=state)  # no second static solve
            first_dt = choice.config.solver.max_dt if is_fixed_step(choice.config.solver) else 0.0
            self._state[name] = SceneState(choice.config, choice.reasons, omega, vec,
                                           first_dt=first_dt)

    # --- compiled pieces -------------------------------------------------------------------

    def _equilibrium(self, name: str, x) -> np.ndarray:
        """[n_blocks, 3] the static equilibrium of design `x` under scene `name`'s closed stages
        (`run.prestressed_state`, which keeps the last ones found, failures too); raises
        `SimulationError` when it does not converge."""
        return prestressed_state(self.task.scenes[name].with_design(np.asarray(x, np.float64)))

    def _static(self, name: str) -> bool:
        """Whether scene `name` starts from a static pre-compression."""
        loading = self.task.scenes[name].loading
        return loading.strain > 0.0 and loading.is_static

    def _frequency(self, name: str, x, vector, state=None):
        scene = self.task.scenes[name]
        if name not in self._estimators:
            self._estimators[name] = make_frequency_estimator(scene, STEP_CHECK_ITERATIONS)
        est = self._estimators[name]
        rounds = 1
        if vector is None:
            vector, rounds = initial_vector(scene), INITIAL_ITERATIONS // STEP_CHECK_ITERATIONS
        v = jnp.asarray(vector)
        for _ in range(rounds):
            omega, v = est(jnp.asarray(x), v, state)
        return float(omega), np.asarray(v)

    def _function(self, name: str, config: SolverConfig) -> "_ScenePrograms":
        """The scene's compiled objective `(x, material, loading, ts, weights, initial,
        equilibrium)` as two programs, the forward pass `-> (value, aux, pullback)` and the
        reverse pass `(pullback, 1.0) -> gradient`, so that a solve the policy rejects is not
        also differentiated (`driver.solve_with_policy(finish=)`), the objective itself
        `-> (value, aux)`, not compiled (`benchmarks/bench_reverse_split.py` sets its fused value
        and gradient beside the two), and the same two passes of the solve from a given static
        equilibrium `((x, q_s), material, loading, ts, weights)`, whose reverse pass gives the
        gradient in x and the cotangent on q_s (see `_solve`)."""
        scene = self.task.scenes[name]
        terms = [t for t in self.task.terms if t.scene == name]
        key = compile_key(scene, config, "task", scene.sample_times) + tuple(
            (t.quantity, tuple(self.task.targets[t.target])) for t in terms) + (
            None if self.task.spin_point is None else tuple(self.task.spin_point),)
        # kept for the process, shared by every evaluator: the weights are arguments, so the
        # runs of a sweep (other weights, other starts) reuse them
        def build():  # under the cache's lock, so the count is exact with several threads
            self.compilations += 1
            return self._program(name, config)

        return cached_program(key, build)[0]

    def _program(self, name: str, config: SolverConfig):
        """`_function`'s programs, built."""
        scene = self.task.scenes[name]
        terms = [t for t in self.task.terms if t.scene == name]
        sim = make_simulator(scene.lattice, scene.supports, config, scene.sample_times,
                             model=scene.model)
        targets = [np.asarray(self.task.targets[t.target]) for t in terms]
        quantities = [t.quantity for t in terms]
        point = None if self.task.spin_point is None else jnp.asarray(self.task.spin_point)

        def objective(x, material, loading, ts, weights, initial=None, equilibrium=None):
            sol = sim(x, material, loading, ts, initial, equilibrium)
            raw = [objective_term(q, sol, ids, point) for q, ids in zip(quantities, targets)]
            value = sum(weights[k] * OPTIMISER_SCALE[q] * raw[k] for k, q in enumerate(quantities))
            aux = dict(solve_health(sol), terms=jnp.stack(raw))
            return value, aux

        def from_start(xq, material, loading, ts, weights):
            x, q_s = xq  # the start state at rest in q_s, differentiated as an input
            return objective(x, material, loading, ts, weights, (q_s, jnp.zeros_like(q_s)))

        return _ScenePrograms(*split_gradient(objective), objective, *split_gradient(from_start))

    def _budgeted(self, config: SolverConfig, name: str, x) -> SolverConfig:
        """`config` as this evaluator solves scene `name` at design `x`: if adaptive, with the
        task's step budget, as an optimiser's gradient needs it (`policy.for_gradient`; a fixed
        step's count is set by its step and the window)."""
        if self.forced is not None or is_fixed_step(config.solver):
            return config
        config = dataclasses.replace(config, max_steps=min(config.max_steps,
                                                           self.max_solve_steps))
        scene = self.task.scenes[name].with_design(np.asarray(x, np.float64))
        return for_gradient(config, scene)

    @staticmethod
    def _record(config: SolverConfig, why: list[str]) -> dict:
        """What an evaluation records of the configuration that counted, as `_solve` solved
        with it (`_budgeted`)."""
        return {"config": config_summary(config), "why": why}

    def _solve(self, name: str, config: SolverConfig, x: np.ndarray, equilibrium=None):
        """The forward pass of one value-and-gradient solve: `(value, pending gradient, term
        values, aux)`, the gradient by `_gradient` (pending: the configuration, the reverse
        pass, its pullback and seed, and the static start). Raises `SimulationError` on any
        failure (`StepBudgetError` when an adaptive solve used up the task's step budget).

        `equilibrium`: the design's static equilibrium in the free DOFs, solved already
        (`run.static_equilibrium`). The solve starts from it at rest, taking it as an input of
        its programs; its residual goes into the solve's health (a start that is not this
        design's equilibrium is refused in one line), and `_gradient` pulls the cotangent on it
        back to the
        design (`run.static_start`, one pair of programs per scene): the configuration's own
        programs then hold no Hessian of the equilibrium (README, "Static pre-compression")."""
        scene = self.task.scenes[name]
        config = self._budgeted(config, name, x)
        programs = self._function(name, config)
        terms = [t for t in self.task.terms if t.scene == name]
        x = jnp.asarray(x)
        rest = (scene.material, scene.loading, jnp.asarray(scene.sample_times),
                self._weights(name))
        if equilibrium is None:
            value, aux, pullback = jax.block_until_ready(programs.forward(x, *rest))
            reverse, start = programs.reverse, None
        else:
            q_s = jnp.asarray(equilibrium)
            value, aux, pullback = jax.block_until_ready(
                programs.forward_from_start((x, q_s), *rest))
            # the start's residual in the solve's health, judged by `checked` as a start solved
            # inside the program is
            aux = dict(aux, static_residual=static_start(scene, config).residual(
                x, scene.material, scene.loading, q_s))
            reverse, start = programs.reverse_from_start, (name, x, q_s)
        checked((value, aux), config)
        values = {t.name: float(v) for t, v in zip(terms, np.asarray(aux["terms"]))}
        return float(value), (config, reverse, pullback, jnp.ones_like(value), start), values, aux

    def _gradient(self, pending) -> np.ndarray:
        """[n_design] the gradient of a forward pass `_solve` returned (its reverse pass, and
        for a solve from a static equilibrium the pullback through it); raises
        `SimulationError` when it is not finite."""
        config, reverse, pullback, seed, start = pending
        grad = reverse(pullback, seed)
        if start is not None:
            name, x, q_s = start
            scene = self.task.scenes[name]
            grad = grad[0] + static_start(scene, config).pullback(
                x, scene.material, scene.loading, q_s, grad[1])
        grad = np.asarray(grad, np.float64)
        if not np.all(np.isfinite(grad)):
            raise SimulationError("non-finite gradient")
        return grad

    def _weights(self, name: str):
        """The weights of the scene's terms, in the order its compiled objective takes them."""
        return jnp.asarray([t.weight for t in self.task.terms if t.scene == name])

    # --- the policy ------------------------------------------------------------------------

    def _check_step(self, name: str, st: SceneState, x: np.ndarray) -> tuple[SceneState, str]:
        """The scene's state after re-checking its fixed step against design `x` (and the
        event to log, or ""); raises `SimulationError` when no stable fixed step exists (or
        the design's static equilibrium was not found)."""
        solver = st.config.solver
        if not (is_fixed_step(solver) and solver.stability_limited):
            return st, ""
        # at the state this design's solve starts from: its own static pre-compression (the
        # previous design's, where the barrier is stiff, overstated it up to 87-fold on a
        # focus-vs-protect run), else rest
        start = self._equilibrium(name, x) if self._static(name) else None
        omega, vector = self._frequency(name, x, st.vector, start)
        if not (np.isfinite(omega) and omega > 0.0 and np.all(np.isfinite(vector))):
            # the stiffness at the start state is not positive definite along the iterate (or
            # the design is damaged): no stable fixed step exists; this design gets the fallback
            raise SimulationError(f"the highest natural frequency of this design came out "
                                  f"{omega:g} rad/ms: no stable fixed step")
        st = dataclasses.replace(st, omega=omega, vector=vector)
        limit = 2.0 / omega  # Verlet's stability limit
        dt = solver.max_dt
        if dt <= STEP_RECHECK * stability_limit(omega, solver):
            return st, ""
        new_dt = fixed_step(omega, solver)
        hz = omega / (2 * np.pi) * 1e3
        if new_dt < MIN_STEP_FRACTION * st.first_dt:
            # the contact barrier sets that frequency: a fixed step would need many times the
            # steps (and the memory of their reverse pass); the adaptive solver places small
            # steps only where the barrier is stiff
            return dataclasses.replace(
                st, config=contact_config(), last_config=None,
                reasons=st.reasons + ("the contact barrier raised the highest natural frequency: "
                                      "adaptive Dopri8",)), (
                f"{name}: highest natural frequency rose to {hz:.0f} Hz; a fixed step of "
                f"{new_dt * 1e3:.1f} us would be below {MIN_STEP_FRACTION:g} x the first one "
                f"({st.first_dt * 1e3:.1f} us): adaptive Dopri8 from here on")
        # reasons[1] is the choice's line about the step (`policy.choose_config`)
        line = step_reason(new_dt, solver, current=True)
        # the last configuration, in contact, continues at the new step with its contact
        # substeps (it would only be re-reached through a rejected solve and two compilations)
        last = st.last_config
        if last is not None and last.use_contact and is_fixed_step(last.solver):
            last = dataclasses.replace(last, solver=dataclasses.replace(
                last.solver, max_dt=new_dt, refined=False))
        else:
            last = None  # its step is the old one
        return dataclasses.replace(
            st, config=dataclasses.replace(st.config, solver=solver.with_max_dt(new_dt)),
            last_config=last,
            reasons=st.reasons[:1] + (line,) + st.reasons[2:]), (
            f"{name}: highest natural frequency rose to {hz:.0f} Hz; fixed step "
            f"{dt * 1e3:.1f} us was {dt / limit:.2f} x Verlet's stability limit, re-chosen to "
            f"{new_dt * 1e3:.1f} us")

    def _solve_scene(self, name: str, st: SceneState, x: np.ndarray):
        """One scene's value, gradient and terms at `x` under the policy, with the record of
        the configuration that counted, the events, the scene's next state and how many solves
        started ahead went unused.
        Raises `EvaluationFailed` (with the state to keep) when every configuration failed."""
        scene = self.task.scenes[name]
        if self.forced is not None:
            try:
                value, pending, terms, _ = self._solve(name, st.config, x)
                grad = self._gradient(pending)
            except SimulationError as exc:
                raise EvaluationFailed(f"{name}: {exc}") from None
            return _SceneOutcome(value, grad, terms, self._record(pending[0], list(st.reasons)),
                                 [], st, 0)

        events: list[str] = []
        checked = [st]  # the state after the step check (kept even when the design fails)

        def check():
            checked[0], event = self._check_step(name, st, x)
            events.extend([event] if event else [])
            return checked[0].config

        def solve(config):
            start = static_equilibrium(scene, config, x) if self._static(name) else None
            value, pending, terms, aux = self._solve(name, config, x, start)
            return (value, pending, terms, aux), aux

        def finish(result):  # the reverse pass, for the solve that counts only (and its
            # configuration as solved, for the record)
            value, pending, terms, aux = result
            return value, self._gradient(pending), terms, aux, pending[0]

        def log(step):
            events.append(f"{name}: {step.error}; {step.reason}" if step.error
                          else f"{name}: {step.reason}")

        try:
            out = solve_with_policy(scene, st.config, solve, check=check,
                                    previous=lambda: (checked[0].last_config,
                                                      checked[0].last_health),
                                    budget_fails_at_once=True, objective=lambda r: r[0],
                                    on_step=log, finish=finish, ahead=self._ahead)
        except PolicyFailed as exc:
            raise EvaluationFailed(f"{name}: {exc}", checked[0]) from None
        st = checked[0]
        value, grad, terms, _, counted = out.result
        why = list(st.reasons) + [s.reason for s in out.steps[1:]]
        if not out.fell_back:
            # the health of the solve that counted, with its half-step estimate where judged
            # so (the driver's `previous`: whether the step stood on it)
            st = dataclasses.replace(st, last_config=out.config, last_health={
                k: np.asarray(v) for k, v in out.health.items()})
        record = self._record(counted, why)
        if "step_error" in out.health:  # the half-step check judged the solve that counted
            record["step_error"] = float(out.health["step_error"])
        return _SceneOutcome(value, grad, terms, record, events, st, out.unused_ahead)

    def evaluate(self, x: np.ndarray) -> Evaluation:
        """Value and gradient of the scalarised objective at design `x` [n_design] (mm).

        Raises:
            EvaluationFailed: when every configuration failed (the reason is in the message).
        """
        start = time.perf_counter()
        events: list[str] = []
        value, grad, terms, solver = 0.0, np.zeros(self.task.lattice.n_design), {}, {}
        unused = 0
        x = np.asarray(x, np.float64)
        names = [n for n in self.task.scenes if any(t.scene == n for t in self.task.terms)]

        def scene(name):
            try:
                return self._solve_scene(name, self._state[name], x)
            except EvaluationFailed as exc:
                return exc

        # one after the other (lazily: a failed scene ends the evaluation), or side by side,
        # every scene waited for; either way taken in the task's order
        parallel = self._scenes is not None and len(names) > 1
        if parallel and self.forced is None:  # (a forced configuration may need none)
            self._equilibria_first(names, x)
        outs = list(self._scenes.map(scene, names)) if parallel else map(scene, names)
        for name, out in zip(names, outs):
            if isinstance(out, EvaluationFailed):
                if out.state is not None:
                    self._state[name] = out.state
                raise out
            self._state[name] = out.state
            unused += out.ahead_unused
            events += out.events
            value, grad = value + out.value, grad + out.grad
            terms.update(out.terms)
            solver[name] = out.record
        return Evaluation(value=value, grad=grad, terms=terms, solver=solver,
                          events=tuple(events), sim_s=time.perf_counter() - start,
                          ahead_unused=unused)

    def _equilibria_first(self, names: list[str], x: np.ndarray) -> None:
        """Solve the static equilibria of design `x` for scenes `names`, one after the other,
        before the scenes' solves go side by side (each scene then finds its own kept,
        `run.prestressed_state`; a failure too, which the scene raises as it would have). A
        static solve's factorisations use every core that is free: on a focus-vs-protect run's
        designs the 8 % equilibrium took 0.8-1.8 s alone and 2.3-3.1 s beside the 1 % scene's
        solves (README, "The static equilibria first")."""
        for name in names:
            if self._static(name):
                try:
                    self._equilibrium(name, x)
                except SimulationError:
                    pass  # kept as the failure the scene's own step check raises

    def close(self) -> None:
        """Let the evaluator's threads go (`threads` > 1): queued solves are dropped, one under
        way (a half-step solve started ahead) ends on its own; it evaluates no more. Also
        `with TaskEvaluator(...) as ev:`."""
        for pool in (self._scenes, self._ahead):
            if pool is not None:
                pool.shutdown(wait=False, cancel_futures=True)

    def __enter__(self) -> "TaskEvaluator":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def configurations(self) -> dict[str, dict]:
        """Scene name -> the configuration currently chosen for it and why."""
        return {k: {"config": config_summary(s.config), "why": list(s.reasons)}
                for k, s in self._state.items()}


__all__ = ["TaskEvaluator", "Evaluation", "EvaluationFailed", "term_value", "task_terms"]
