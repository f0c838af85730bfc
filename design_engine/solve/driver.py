"""The one driver of the solver policy: solve, judge, re-solve or fall back, and say why.

Every user of the policy (a forward run of a scene, an objective for an optimiser, a task's
evaluator, the pulse calibration's fits, and, point by point, the batched robustness map) goes
through `decide` (what to do after a solve) and, for one solve at a time, `solve_with_policy`
(the loop around it). The decisions themselves live in `policy` (`start_config`, `next_config`,
`fallback_config`); this module only sequences them:

1. start with the caller's configuration, or with the one the previous evaluation ended with
   while that was in contact (`policy.start_config`, optimisers only);
2. after a solve that did not fail, `policy.next_config` says whether the result stands or which
   configuration solves again (contact, half the step, Dopri8); a fixed step with contact whose
   voids reached the contact cutoff (at its start or under the pulse) and that passed the
   other checks is first also judged on the caller's objective at half its step (`objective`,
   `policy.needs_step_check`) and, when it moved too much, at a quarter, the half- or
   quarter-step solve standing in its place where its own error passes
   (`policy.after_half_step`, `policy.after_quarter_step`); a fourth-order one at COARSE x its
   step and, when it moved too much, at half its step, which stands where its error by that
   pair passes (`policy.check_config`, `policy.after_coarse_check`);
3. after a fixed-step solve with contact that failed, the same start at half the step (the
   fourth order) or with its contact forces substepped (Verlet; `policy.after_failure`,
   once); after any other solve that failed (`SimulationError`), the fallback solves once
   (`policy.fallback_config`; the reference Dopri5 when the fallback itself failed), except
   that an adaptive solve which used up its step budget fails at once when the caller asks so
   (an optimiser steps back rather than grinding on a near-singular contact);
4. a fallback that fails too raises.

With an executor (`ahead`), the check's solve that step 2 will most likely ask for (half the
step, or 1.5 x it for the fourth order: `policy.check_config`; the
previous evaluation's solve reached contact: `policy.needs_step_check` on its health) runs
on another thread while the step itself is solved: XLA runs each of these programs on one core,
so on two cores the check costs the longer of the two solves, not their sum. It is taken where
the policy asks for that configuration (the check, or a re-solve at half the step) and
otherwise waited for and dropped, so the sequence of decisions and the result are the same as
without it; `Outcome.unused_ahead` counts the dropped solves that had run (the work lost).
While it runs, the step's own reverse pass (`finish`) is taken on this thread, before the
check's verdict: where the step stands (most often) its gradient is ready when the check
ends, and where it does not the early reverse pass is wasted and the solve that stands is
finished as without the executor. It is taken so where the previous evaluation's solve
stood at the same step on its own check (`_likely_to_stand`): on the 60-evaluation focusing
run 102 s against 119 s, the same path (`benchmarks/results/bench_focusing_run_spec.json`).

What happened comes back as a typed record (`Outcome`, a tuple of `Step`), not as strings.
"""

from collections.abc import Callable
from concurrent.futures import Executor, Future
from dataclasses import dataclass, replace
from typing import Generic, TypeVar

from design_engine.physics.scenes import Scene
from design_engine.solve.fixed_step import is_fixed_step
from design_engine.solve.policy import (COARSE_CHECK_ORDER, HALF, REFINE, REJECT,
                                        STEP_ERROR_TOLERANCE, after_coarse_check, after_failure,
                                        after_half_step, after_quarter_step, check_config,
                                        check_ratio, coarse_step_error,
                                        fallback_config, half_step_pair_error, moved,
                                        needs_step_check, next_config, order_of, refined,
                                        relative_step_error, start_config)
from design_engine.solve.simulate import SimulationError, SolverConfig, StepBudgetError

R = TypeVar("R")

START = "start"  # the configuration the solve starts with
CONTINUED = "continued"  # the previous evaluation's configuration, kept while in contact
RESOLVE = "resolve"  # `policy.next_config` rejected the last result
FALLBACK = "fallback"  # the last solve failed
REFERENCE_RETRY = "retried with the reference Dopri5 configuration"
CONTINUED_REASON = "the previous design needed contact: started with its configuration"


@dataclass(frozen=True)
class Step:
    """One configuration the driver solved with, and why."""

    kind: str  # START, CONTINUED, RESOLVE or FALLBACK
    config: SolverConfig
    reason: str
    error: str = ""  # for FALLBACK, or a RESOLVE after a failure: the failure of the solve before


@dataclass(frozen=True)
class Outcome(Generic[R]):
    """A solve under the policy: its result, the configuration that counted and every step."""

    result: R
    health: dict | None  # `simulate.solve_health` of the counted solve (None if not given)
    steps: tuple[Step, ...]
    # half-step solves started ahead (`solve_with_policy(ahead=)`) that ran and were not asked
    # for: the work the speculation lost
    unused_ahead: int = 0

    @property
    def config(self) -> SolverConfig:
        return self.steps[-1].config

    @property
    def resolves(self) -> tuple[str, ...]:
        """The reasons of every solve after the first (re-solves and fallbacks)."""
        return tuple(f"{s.reason} ({s.error})" if s.error else s.reason
                     for s in self.steps if s.kind in (RESOLVE, FALLBACK))

    @property
    def fell_back(self) -> bool:
        return self.steps[-1].kind == FALLBACK


class PolicyFailed(SimulationError):
    """Every configuration the policy allowed failed (or the step budget was used up with
    `budget_fails_at_once`). `steps` says what was tried."""

    def __init__(self, message: str, steps: tuple[Step, ...], budget: bool = False):
        super().__init__(message)
        self.steps = steps
        self.budget = budget


def decide(config: SolverConfig, scene: Scene, *, health: dict | None = None,
           error: SimulationError | None = None, fallen_back: bool = False,
           budget_fails_at_once: bool = False,
           fallback: SolverConfig | None = None) -> Step | None:
    """What follows a solve with `config`: None when its result stands, else the next `Step`.

    Give `health` (`simulate.solve_health`) after a solve that did not fail, `error` after one
    that did. `fallback` replaces `policy.fallback_config()` (a caller whose derivatives need
    another adjoint). Raises `PolicyFailed` when nothing may follow a failure (a fallback that
    failed, or a used-up step budget under `budget_fails_at_once`).
    """
    if error is None:
        if health is None:
            return None
        nxt = next_config(config, health, scene)
        return None if nxt is None else Step(RESOLVE, nxt[0], nxt[1])
    if fallen_back:
        raise PolicyFailed(f"the fallback failed too: {error}", ())
    if (budget_fails_at_once and isinstance(error, StepBudgetError)
            and not is_fixed_step(config.solver)):
        raise PolicyFailed(f"{error}; over the evaluation's step budget "
                           "(budget.max_solve_steps): the design counts as failed, with no "
                           "fallback", (), budget=True)
    retry = after_failure(config)
    if retry is not None:  # a fixed step with contact: the barrier most likely outgrew it
        return Step(RESOLVE, retry[0], retry[1], str(error))
    fb, reason = fallback_config()
    fb = fallback or fb
    if config == fb:
        fb, reason = SolverConfig(), REFERENCE_RETRY
    return Step(FALLBACK, fb, reason, str(error))


def _likely_to_stand(config: SolverConfig, last: SolverConfig | None,
                     health: dict | None) -> bool:
    """Whether a fixed step is expected to pass its half-step check: the previous evaluation's
    solve that counted was the same configuration and stood on its own check. A step climbing
    back toward the chosen one is not (on a focus-vs-protect replay such climbs were rejected,
    and their early reverse passes cost up to 5.4 s an evaluation)."""
    return (last == config and health is not None
            and float(health.get("step_error", float("inf"))) <= STEP_ERROR_TOLERANCE)


def _attempt(finish, result):
    """`finish(result)`, or the `SimulationError` it raised."""
    try:
        return finish(result)
    except SimulationError as exc:
        return exc


def _judged_at_half_steps(scene: Scene, steps: list, result, health: dict, solve, objective,
                          on_step) -> tuple:
    """Judge a fixed-step solve that `policy.needs_step_check` names (the last of `steps`,
    with `result` and `health`) on the caller's `objective`, by the same start solved with
    `solve` at half its step and, where `policy.after_half_step` says so, at a quarter:
    returns the `(result, health)` that goes on to `policy.next_config`, `health["step_error"]`
    being its estimate (and "half_step_error" the half-step solve's, where it was judged at a
    quarter and did not stand). A half- or quarter-step solve that `policy.after_quarter_step` lets
    stand is appended to `steps` as a RESOLVE and returned (it is not solved again). A
    half-step solve that fails leaves the result untrusted at its step (inf)."""
    cfg = steps[-1].config
    half = refined(cfg)
    try:
        half_result, half_health = solve(half)
        error = relative_step_error(float(objective(result)), float(objective(half_result)))
    except SimulationError:
        return result, dict(health, step_error=float("inf"))
    health = dict(health, step_error=error)
    if (next_config(cfg, health, scene) is None
            or after_half_step(error, half, half_health, scene) == REJECT):
        return result, health
    quarter = refined(half)
    try:
        quarter_result, quarter_health = solve(quarter)
        half_error = relative_step_error(float(objective(half_result)),
                                         float(objective(quarter_result)))
    except SimulationError:
        return result, dict(health, half_step_error=float("inf"))
    verdict, reason = after_quarter_step(error, half_error, half, quarter, quarter_health, scene)
    if verdict == REJECT:
        return result, dict(health, half_step_error=half_error)
    if verdict == HALF:
        return _stands(steps, half, reason, on_step, half_result,
                       dict(half_health, step_error=half_error))
    return _stands(steps, quarter, reason, on_step, quarter_result,
                   dict(quarter_health, step_error=half_error * REFINE**2))


def _stands(steps: list, config: SolverConfig, reason: str, on_step, result, health) -> tuple:
    """A judging solve (`config`, its `result` and `health`) that stands in place of the one it
    judged: appended to `steps` as a RESOLVE (and shown to `on_step`); returns (result, health)."""
    steps.append(Step(RESOLVE, config, reason))
    if on_step is not None:
        on_step(steps[-1])
    return result, health


def _judged_at_another_step(scene: Scene, steps: list, result, health: dict, solve, objective,
                              on_step) -> tuple:
    """Judge a fourth-order fixed-step solve as `_judged_at_half_steps` judges Verlet's, by the
    same start solved at `policy.check_ratio` x its step (`policy.check_config`: COARSE, or
    1 / COARSE where the step is marked `finer_check`; its estimate `policy.coarse_step_error`
    into the health as "step_error", inf where that solve failed). Where that does not pass,
    the solve that may stand in its place (appended to `steps` as a RESOLVE) is the finer
    check itself, where the step was judged so, when its own error by the pair passes (the
    change over COARSE^COARSE_CHECK_ORDER - 1); else, where `policy.after_coarse_check` says
    so, the same start at half the step, when its error by the pair
    (`policy.half_step_pair_error`, its "step_error") passes, with its other checks; else the
    result goes on with "half_step_error" set (then Dopri8)."""
    cfg = steps[-1].config
    value = float(objective(result))
    ratio = check_ratio(cfg)
    check = check_config(cfg)
    try:
        check_result, check_health = solve(check)
        check_value = float(objective(check_result))
        error = coarse_step_error(value, check_value, ratio)
    except SimulationError:
        check_result, error = None, float("inf")
    health = dict(health, step_error=error)
    if next_config(cfg, health, scene) is None:
        return result, health
    why = moved(error, order=order_of(cfg.solver), ratio=ratio)
    if ratio < 1.0:  # the finer solve is the candidate
        if check_result is None:
            return result, health
        own = relative_step_error(check_value, value, 1.0 / ratio, COARSE_CHECK_ORDER)
        return _in_its_place(scene, steps, result, health, (check, check_result, check_health),
                             own, f"{why}: the finer solve", on_step)
    if not after_coarse_check(error, cfg):
        return result, health
    half = refined(cfg)
    try:
        half_result, half_health = solve(half)
        half_error = half_step_pair_error(float(objective(half_result)), value)
    except SimulationError:
        return result, dict(health, half_step_error=float("inf"))
    return _in_its_place(scene, steps, result, health, (half, half_result, half_health),
                         half_error, f"{why}: the half-step solve", on_step)


def _in_its_place(scene: Scene, steps: list, result, health: dict, candidate: tuple,
                  own: float, what: str, on_step) -> tuple:
    """The fourth-order solve judged (`result`, `health`, "half_step_error" set to `own`), or
    `candidate` (configuration, result, health) standing in its place (`_stands`) where its
    own error by the pair, `own`, and its other checks pass. `what` says which solve."""
    config, candidate_result, candidate_health = candidate
    candidate_health = dict(candidate_health, step_error=own)
    if next_config(config, candidate_health, scene) is not None:
        return result, dict(health, half_step_error=own)
    return _stands(steps, config, (
        f"{what} ({config.solver.max_dt * 1e3:.1f} us) stands, its error by that pair "
        f"{own:.2e}"), on_step, candidate_result, candidate_health)


def solve_with_policy(scene: Scene, config: SolverConfig,
                      solve: Callable[[SolverConfig], tuple[R, dict | None]], *,
                      check: Callable[[], SolverConfig] | None = None,
                      previous: Callable[[], tuple[SolverConfig | None, dict | None]]
                      | None = None,
                      budget_fails_at_once: bool = False,
                      fallback: SolverConfig | None = None,
                      objective: Callable[[R], float] | None = None,
                      on_step: Callable[[Step], None] | None = None,
                      finish: Callable[[R], R] | None = None,
                      ahead: Executor | None = None) -> Outcome[R]:
    """Solve under the policy, starting from `config` (the choice for this scene).

    `solve(config) -> (result, health)` runs one solve and raises `SimulationError` on failure;
    `health` (`simulate.solve_health` scalars, or None to skip the judging) feeds
    `policy.next_config`. `check() -> config`, when given, re-checks the configuration before
    the first solve (an optimiser's fixed-step check); its `SimulationError` counts as a failed
    solve. `previous() -> (config, health)`: what the caller's last evaluation ended with
    (optimisers: `policy.start_config` may continue with it), asked after `check`, whose
    re-checked step the continued configuration must take. `fallback` replaces the policy's
    fallback configuration. `objective(result) -> float`: the caller's objective of a result;
    with it, a solve that `policy.needs_step_check` names once it passed the other checks is
    also solved at half its step by `solve` and judged by the change of the objective
    (`_judged_at_half_steps`: Richardson-scaled into the health as "step_error"; a half- or
    quarter-step solve whose own error passes stands in its place, not solved again).
    `on_step` sees each step after the first as it is taken
    (event logs). `finish(result) -> result`: the part of a solve that only the result that
    stands needs (an optimiser's reverse pass: `solve` returns the forward pass and what the
    reverse one needs, so that a rejected solve does not pay for its gradient); its
    `SimulationError` counts as that solve's failure. `ahead`: an executor on which the
    half-step solve the check most likely needs (see the module docstring) is started beside
    the step's own solve, and the step's `finish` taken while it runs; `solve` and `finish`
    must then be safe to call from two threads. Raises
    `PolicyFailed` when every allowed configuration failed.
    """
    early: list[tuple[SolverConfig, Future]] = []  # half-step solves started ahead

    def solved(cfg: SolverConfig):
        """`solve(cfg)`, or the result of the same solve started ahead (solved here when it
        has not started yet)."""
        for k, (started, future) in enumerate(early):
            if started == cfg:
                del early[k]
                return solve(cfg) if future.cancel() else future.result()
        return solve(cfg)

    def drop(wait: bool) -> int:
        """Solves started ahead and not asked for: cancelled, or waited for (so that they do
        not run into the caller's next solve) unless interrupted. Returns how many had
        started (could not be cancelled)."""
        ran = 0
        for _, future in early:
            if not future.cancel():
                ran += 1
                if wait:
                    future.exception()
        return ran

    def start_ahead(cfg: SolverConfig) -> bool:
        """Start `solve(cfg)` on the executor, unless one started ahead is still pending;
        whether `solve(cfg)` is now under way there."""
        if not early:
            early.append((cfg, ahead.submit(solve, cfg)))
        return any(started == cfg for started, _ in early)

    try:
        outcome = _solve_with_policy(scene, config, solved, check, previous,
                                     budget_fails_at_once, fallback, objective, on_step, finish,
                                     None if ahead is None else start_ahead)
    except Exception:
        drop(wait=True)
        raise
    except BaseException:  # an interrupt does not wait for a solve nobody will use
        drop(wait=False)
        raise
    unused = drop(wait=True)
    return replace(outcome, unused_ahead=unused) if unused else outcome


def _solve_with_policy(scene, config, solve, check, previous, budget_fails_at_once, fallback,
                       objective, on_step, finish, ahead) -> Outcome:
    """`solve_with_policy`'s loop; `ahead(config)`: start that solve on the executor (`solve`
    takes it from there)."""
    pending, prior, last = None, None, None
    if check is not None:
        try:
            config = check()
        except SimulationError as exc:
            pending = exc
    steps = [Step(START, config, "")]
    if pending is None and previous is not None:
        last, prior = previous()
        start = start_config(config, last, prior, scene)
        if start != config:
            steps.append(Step(CONTINUED, start, CONTINUED_REASON))
    finished = None  # (result, its finish() or the SimulationError it raised), taken early
    while True:
        cfg, fallen_back = steps[-1].config, steps[-1].kind == FALLBACK
        if pending is None:
            beside = (ahead is not None and objective is not None and prior is not None
                      and not fallen_back and needs_step_check(cfg, prior, scene)
                      and ahead(check_config(cfg)))
            finished = None  # a result solved before, and its reverse pass, let go
            try:
                result, health = solve(cfg)
            except SimulationError as exc:
                pending = exc
            else:
                if (objective is not None and health is not None and not fallen_back
                        and needs_step_check(cfg, health, scene)
                        and next_config(cfg, health, scene) is None):
                    if beside and finish is not None and _likely_to_stand(cfg, last, prior):
                        # the half-step solve that judges this one runs on the other thread:
                        # take this one's reverse pass meanwhile (wasted, and not used, where
                        # the check does not let it stand)
                        finished = (result, _attempt(finish, result))
                    judge = (_judged_at_half_steps if order_of(cfg.solver) == 2
                             else _judged_at_another_step)
                    result, health = judge(scene, steps, result, health, solve, objective,
                                           on_step)
                    cfg = steps[-1].config
                    if finished is not None and finished[0] is not result:
                        finished = None
        if pending is not None:
            try:
                step = decide(cfg, scene, error=pending, fallen_back=fallen_back,
                              budget_fails_at_once=budget_fails_at_once, fallback=fallback)
            except PolicyFailed as failed:
                message = f"{steps[-1].error}; {failed}" if fallen_back else str(failed)
                raise PolicyFailed(message, tuple(steps), failed.budget) from None
            pending = None
        else:
            # a fallback's result stands: it is the reference the others are judged against
            step = None if fallen_back else decide(cfg, scene, health=health)
            if step is None:
                if finish is None:
                    return Outcome(result, health, tuple(steps))
                try:
                    if finished is not None and finished[0] is result:
                        done = finished[1]
                        if isinstance(done, SimulationError):
                            raise done
                        return Outcome(done, health, tuple(steps))
                    return Outcome(finish(result), health, tuple(steps))
                except SimulationError as exc:
                    pending = exc  # judged as the failure of this solve
                    continue
        steps.append(step)
        if on_step is not None:
            on_step(step)


__all__ = ["Outcome", "PolicyFailed", "Step", "decide", "solve_with_policy"]
