"""The one policy driver (`solve.driver`): what it solves with, in which order, and what it says.

The solves here are stand-ins that return chosen health figures or raise, so that every branch
of the sequencing is reached in milliseconds; the decisions themselves are the real policy's
(`policy.next_config`, `policy.start_config`, `policy.fallback_config`) on a real scene. The
five users run real solves through it in test_stability, test_design, test_robustness and
test_calibrate.
"""

import dataclasses

import diffrax
import pytest

from design_engine.physics.scenes import build_scene
from design_engine.solve.driver import (CONTINUED, FALLBACK, REFERENCE_RETRY, RESOLVE, START,
                                        PolicyFailed, decide, solve_with_policy)
from design_engine.solve.fixed_step import FixedStepVerlet
from design_engine.solve.policy import (CHECKPOINT_BYTES_PER_DOF, CONTACT_ENTRY_SUBSTEPS,
                                        CONTACT_ORDER,
                                        ENERGY_TOLERANCE, GRADIENT_ATOL,
                                        GRADIENT_CHECKPOINT_BYTES, REFINE, contact_config,
                                        fallback_config, for_gradient, refined, start_config,
                                        start_in_contact, with_contact)
from design_engine.solve.run import config_summary
from design_engine.solve.simulate import SimulationError, SolverConfig, StepBudgetError

VERLET = SolverConfig(solver=FixedStepVerlet(max_dt=0.01), use_contact=False)
# Verlet itself with contact (the policy's `with_contact` takes the fourth order): the
# second-order step's own judge, at half and a quarter of its step
VERLET_CONTACT = SolverConfig(solver=FixedStepVerlet(max_dt=0.01, contact_substeps=4),
                              use_contact=True)


@pytest.fixture(scope="module")
def scene():
    return build_scene("focusing-24x16", nx=4, ny=3)


def healthy(scene, **over):
    """Health of a solve that stayed clear of contact and kept its energy balance (units of
    unbounded inertia: the contact barrier's frequency never outgrows a step)."""
    span = float(scene.material.contact_cutoff - scene.material.contact_min)
    return {"void_margin": 2.0 * span, "energy_error": 0.0, "min_inertia": float("inf"), **over}


class Script:
    """A stand-in solve: answers each call with the next entry (health dict or exception)."""

    def __init__(self, *answers):
        self.answers, self.calls = list(answers), []

    def __call__(self, config):
        self.calls.append(config)
        answer = self.answers.pop(0)
        if isinstance(answer, Exception):
            raise answer
        return f"result {len(self.calls)}", answer


def test_a_result_that_stands_is_returned_after_one_solve(scene):
    solve = Script(healthy(scene))
    out = solve_with_policy(scene, VERLET, solve)
    assert solve.calls == [VERLET] and out.result == "result 1"
    assert [s.kind for s in out.steps] == [START] and out.resolves == () and not out.fell_back


def test_voids_at_the_cutoff_are_re_solved_with_contact_at_the_same_step(scene):
    solve = Script(healthy(scene, void_margin=0.0), healthy(scene))
    seen = []
    out = solve_with_policy(scene, VERLET, solve, on_step=seen.append)
    assert [s.kind for s in out.steps] == [START, RESOLVE] and seen == [out.steps[1]]
    assert out.config.use_contact and out.config.solver.max_dt == VERLET.solver.max_dt
    assert out.config.solver.contact_substeps == CONTACT_ENTRY_SUBSTEPS
    assert out.config.solver.order == CONTACT_ORDER == 4 and out.config.dtype == VERLET.dtype
    assert "contact cutoff" in out.resolves[0] and "fourth order" in out.resolves[0]
    assert out.result == "result 2"


def test_a_drifting_fixed_step_is_refined_then_handed_to_dopri8(scene):
    drift = healthy(scene, energy_error=0.1 * ENERGY_TOLERANCE * 1e3)  # far beyond refining
    out = solve_with_policy(scene, VERLET, Script(drift, healthy(scene)))
    assert out.config == contact_config() and "Dopri8" in out.resolves[0]
    small = healthy(scene, energy_error=2 * ENERGY_TOLERANCE)  # refining is predicted to pass
    out = solve_with_policy(scene, VERLET, Script(small, small, healthy(scene)))
    assert [s.kind for s in out.steps] == [START, RESOLVE, RESOLVE]
    assert out.steps[1].config.solver.refined and out.steps[1].config.solver.max_dt == 0.005
    assert out.config == contact_config()  # a refined step rejected again: Dopri8


def test_only_the_result_that_stands_is_finished_and_a_failed_finish_is_a_failed_solve(scene):
    """`finish` (an optimiser's reverse pass) runs once, on the result that stands, never on
    one the policy rejected; when it fails, that solve counts as failed (here the fourth order
    with contact: re-solved at half the step)."""
    finished = []

    def finish(result):
        finished.append(result)
        if result == "result 2" and len(finished) == 1 and fail[0]:
            raise SimulationError("non-finite gradient")
        return result + " finished"

    fail = [False]
    solve = Script(healthy(scene, void_margin=0.0), healthy(scene))
    out = solve_with_policy(scene, VERLET, solve, finish=finish)
    assert finished == ["result 2"] and out.result == "result 2 finished"
    finished.clear()
    fail[0] = True
    solve = Script(healthy(scene, void_margin=0.0), healthy(scene), healthy(scene))
    out = solve_with_policy(scene, VERLET, solve, finish=finish)
    assert finished == ["result 2", "result 3"] and out.result == "result 3 finished"
    assert out.steps[-1].error == "non-finite gradient" and "substep" not in out.steps[1].reason
    assert [s.kind for s in out.steps] == [START, RESOLVE, RESOLVE]
    assert out.config == refined(out.steps[1].config)


def test_a_failed_solve_falls_back_once_and_the_fallback_result_stands(scene):
    in_contact = healthy(scene, void_margin=0.0)  # would be re-solved, were it not the fallback
    solve = Script(SimulationError("went non-finite"), in_contact)
    out = solve_with_policy(scene, VERLET, solve)
    assert out.fell_back and out.config == fallback_config()[0] and len(solve.calls) == 2
    assert out.steps[-1].error == "went non-finite"
    assert out.resolves == (f"{fallback_config()[1]} (went non-finite)",)


def test_a_failed_fallback_raises_with_both_reasons_and_every_step(scene):
    solve = Script(SimulationError("first"), SimulationError("second"))
    with pytest.raises(PolicyFailed) as info:
        solve_with_policy(scene, VERLET, solve)
    assert str(info.value) == "first; the fallback failed too: second"
    assert [s.kind for s in info.value.steps] == [START, FALLBACK] and not info.value.budget


def test_an_adaptive_solve_for_a_gradient_takes_the_gradient_tolerance_and_checkpoints(scene):
    """An optimiser's adaptive solves control their error to GRADIENT_ATOL where the pulse
    starts in contact (the reference's 1e-4 left gradient cosines of 0.99986 on a
    focus-vs-protect design at 8 %) and keep the reference's 1e-4 where it starts out of
    contact (cosine 1.0000000 on six designs that enter contact under the pulse, README), and
    store as many states for the reverse pass as GRADIENT_CHECKPOINT_BYTES hold, at most one
    per step of their budget; a tighter atol, an adjoint of the caller's and fixed steps are
    kept."""
    at_rest = for_gradient(contact_config(), scene)
    assert not start_in_contact(scene) and at_rest.atol == contact_config().atol
    assert at_rest.solver == contact_config().solver and at_rest.rtol == contact_config().rtol
    assert at_rest.adjoint.checkpoints == at_rest.max_steps  # a small lattice: one per step
    # 6x6 at 7 %: the equilibrium closes voids past the cutoff (tests/test_stability.py, jammed)
    jammed = build_scene("protection-24x18", nx=6, ny=6, strain=0.07, amplitude_m=2e-3)
    assert start_in_contact(jammed)
    assert for_gradient(contact_config(), jammed).atol == GRADIENT_ATOL < contact_config().atol
    ramp = build_scene("protection-24x18", nx=6, ny=6, strain=0.07, amplitude_m=2e-3,
                       precompression="ramp")
    assert for_gradient(contact_config(), ramp).atol == GRADIENT_ATOL  # no equilibrium solved
    protection = build_scene("protection-24x18")
    assert protection.supports.free.size == 1146
    tight = dataclasses.replace(contact_config(), atol=GRADIENT_ATOL)  # (no equilibrium asked)
    big = for_gradient(tight, protection)
    states = GRADIENT_CHECKPOINT_BYTES // (CHECKPOINT_BYTES_PER_DOF * 1146)
    assert 2000 < states < big.max_steps and big.adjoint.checkpoints == states
    assert config_summary(big)["checkpoints"] == states
    few = for_gradient(dataclasses.replace(tight, max_steps=50), protection)
    assert few.adjoint.checkpoints == 50
    assert for_gradient(SolverConfig(atol=1e-9), jammed).atol == 1e-9
    assert for_gradient(VERLET, scene) == VERLET
    own = SolverConfig(adjoint=diffrax.BacksolveAdjoint())
    assert for_gradient(own, scene).adjoint == own.adjoint


def test_the_fallback_of_the_fallback_configuration_is_the_reference(scene):
    step = decide(contact_config(), scene, error=SimulationError("x"))
    assert step.kind == FALLBACK and step.config == SolverConfig() and step.reason == REFERENCE_RETRY
    own = SolverConfig(rtol=1e-9)
    assert decide(VERLET, scene, error=SimulationError("x"), fallback=own).config == own


def test_a_used_up_step_budget_fails_at_once_only_when_asked_and_only_for_adaptive(scene):
    adaptive = contact_config()
    with pytest.raises(PolicyFailed) as info:
        solve_with_policy(scene, adaptive, Script(StepBudgetError("20000 steps")),
                          budget_fails_at_once=True)
    assert info.value.budget and "step budget" in str(info.value)
    out = solve_with_policy(scene, adaptive, Script(StepBudgetError("20000 steps"),
                                                    healthy(scene)))
    assert out.fell_back  # not asked: the fallback runs
    out = solve_with_policy(scene, VERLET, Script(StepBudgetError("n"), healthy(scene)),
                            budget_fails_at_once=True)
    assert out.fell_back  # a fixed step's count is not a budget


def test_a_failed_check_counts_as_a_failed_solve(scene):
    def check():
        raise SimulationError("no stable fixed step")

    solve = Script(healthy(scene))
    out = solve_with_policy(scene, VERLET, solve, check=check)
    assert solve.calls == [fallback_config()[0]] and out.steps[-1].error == "no stable fixed step"
    checked = SolverConfig(solver=FixedStepVerlet(max_dt=0.004), use_contact=False)
    out = solve_with_policy(scene, VERLET, Script(healthy(scene)), check=lambda: checked)
    assert out.config == checked


def test_an_evaluation_after_one_in_contact_starts_with_contact(scene):
    contact = SolverConfig(solver=VERLET.solver, use_contact=True, dtype="float64")
    solve = Script(healthy(scene, void_margin=0.0))
    out = solve_with_policy(scene, VERLET, solve,
                            previous=lambda: (contact, healthy(scene, void_margin=0.0)))
    assert solve.calls == [contact] and [s.kind for s in out.steps] == [START, CONTINUED]
    # a run that needed a fixed step with contact keeps it when the voids left the cutoff (the
    # full model); Dopri8 only while they reach it
    out = solve_with_policy(scene, VERLET, Script(healthy(scene)),
                            previous=lambda: (contact, healthy(scene)))
    assert out.config == contact
    out = solve_with_policy(scene, VERLET, Script(healthy(scene)),
                            previous=lambda: (contact_config(), healthy(scene)))
    assert out.config == VERLET


def test_a_failed_fixed_step_with_contact_is_retried_once_before_dopri8(scene):
    """A fixed step with contact that diverged most likely met a barrier that outgrew it:
    Verlet's same step with the contact forces substepped CONTACT_SUBSTEPS_MAX times, once, the
    fourth order's same start at half the step, once, then the fallback (a fixed step without
    contact, or one already substepped as much, falls back at once)."""
    from design_engine.solve.policy import CONTACT_SUBSTEPS_MAX

    contact = SolverConfig(solver=VERLET.solver, use_contact=True, dtype="float64")
    solve = Script(SimulationError("the state diverged"), SimulationError("again"),
                   healthy(scene))
    out = solve_with_policy(scene, contact, solve)
    assert [s.kind for s in out.steps] == [START, RESOLVE, FALLBACK] and out.fell_back
    assert solve.calls[1].solver.contact_substeps == CONTACT_SUBSTEPS_MAX
    assert solve.calls[1].solver.max_dt == contact.solver.max_dt and solve.calls[1].use_contact
    assert out.steps[1].error == "the state diverged" and "stepped 8 times" in out.steps[1].reason
    assert out.steps[2].error == "again" and out.config == fallback_config()[0]
    out = solve_with_policy(scene, contact, Script(SimulationError("x"), healthy(scene)))
    assert [s.kind for s in out.steps] == [START, RESOLVE] and not out.fell_back
    assert decide(VERLET, scene, error=SimulationError("x")).kind == FALLBACK
    # the fourth order (its contact forces with the rest): once at half the step, then Dopri8
    fourth = with_contact(VERLET)
    solve = Script(SimulationError("through the barrier"), SimulationError("again"),
                   healthy(scene))
    out = solve_with_policy(scene, fourth, solve)
    assert [s.kind for s in out.steps] == [START, RESOLVE, FALLBACK]
    assert solve.calls[1] == refined(fourth) and solve.calls[1].solver.contact_substeps == 1
    assert "0.5 x the step" in out.steps[1].reason and out.config == fallback_config()[0]


def test_the_continued_configuration_is_read_after_the_check(scene):
    """`previous` as a function is called after `check`, so an evaluation continues with the
    configuration the check left (its re-chosen step), not the one from before it."""
    order = []
    contact = SolverConfig(solver=VERLET.solver, use_contact=True, dtype="float64")

    def check():
        order.append("check")
        return VERLET

    def previous():
        order.append("previous")
        return contact, healthy(scene, void_margin=0.0)

    solve = Script(healthy(scene, void_margin=0.0))
    out = solve_with_policy(scene, VERLET, solve, check=check, previous=previous)
    assert order == ["check", "previous"] and solve.calls == [contact]
    assert [s.kind for s in out.steps] == [START, CONTINUED]


def test_a_solve_in_contact_is_judged_at_half_its_step_too(scene):
    """`needs_step_check`: a fixed step with contact whose voids reached the cutoff, at its
    start or under the pulse; not one whose voids stayed clear of it (the model without
    contact terms, which the work-energy balance bounds). A whole step whose estimate is over STEP_ERROR_TOLERANCE: `after_half_step`
    judges its half-step solve at its own half when the quarter is predicted to pass (the
    estimate x 1/16, Verlet being second order, within half the tolerance) and the half passed
    its other checks; `after_quarter_step` then lets the half stand on its own estimate, or the
    quarter on its error by that pair (x 1/4) where the two changes shrink as a second-order
    step's; else Dopri8, which is also what `next_config` says to a step whose estimate stayed
    over the tolerance."""
    from design_engine.solve.policy import (DEEPER, HALF, QUARTER, REJECT, STEP_ERROR_TOLERANCE,
                                            after_half_step, after_quarter_step,
                                            needs_step_check, next_config)

    tol = STEP_ERROR_TOLERANCE
    span = float(scene.material.contact_cutoff - scene.material.contact_min)
    contact = VERLET_CONTACT
    started = healthy(scene, void_margin=0.5 * span, start_void_margin=0.5 * span)
    assert needs_step_check(contact, started, scene)
    # contact entered under the pulse (the ledger alone let solves 2.6e-4 to 9.7e-4 off J stand
    # on a focus-vs-protect front's 1 % scene: README, "Contact under the pulse")
    assert needs_step_check(contact, healthy(scene, void_margin=0.5 * span,
                                             start_void_margin=2.0 * span), scene)
    assert not needs_step_check(contact, healthy(scene, start_void_margin=2.0 * span), scene)
    assert not needs_step_check(VERLET, started, scene)
    assert not needs_step_check(contact_config(), started, scene)
    assert next_config(contact, dict(started, step_error=0.5 * tol), scene) is None
    for error in (1.5 * tol, float("nan")):
        nxt, why = next_config(contact, dict(started, step_error=error), scene)
        assert nxt == contact_config() and "half the step" in why and "Dopri8" in why
    half, quarter = refined(contact), refined(refined(contact))
    assert after_half_step(8 * tol, half, started, scene) == DEEPER
    assert after_half_step(9 * tol, half, started, scene) == REJECT
    assert after_half_step(float("inf"), half, started, scene) == REJECT
    # a half-step solve that failed another check is not judged further
    assert after_half_step(2 * tol, half, dict(started, energy_error=1.0), scene) == REJECT
    verdict, why = after_quarter_step(3 * tol, 0.9 * tol, half, quarter, started, scene)
    assert verdict == HALF and "half-step solve" in why and "stands" in why
    verdict, why = after_quarter_step(8 * tol, 2 * tol, half, quarter, started, scene)
    assert verdict == QUARTER and "quarter-step solve" in why and "4.0:1" in why
    # changes that do not shrink as the step's order says (the step not yet converging), or a
    # quarter's own error over the tolerance, or a quarter that failed another check: Dopri8
    assert after_quarter_step(3 * tol, 2 * tol, half, quarter, started, scene)[0] == REJECT
    assert after_quarter_step(3 * tol, 0.0, half, quarter, started, scene)[0] == HALF
    assert after_quarter_step(20 * tol, 5 * tol, half, quarter, started, scene)[0] == REJECT
    assert after_quarter_step(8 * tol, 2 * tol, half, quarter, dict(started, energy_error=1.0),
                              scene)[0] == REJECT
    # the next evaluation climbs one halving back toward the chosen step whatever the half-step
    # estimate (the step check's half and quarter solves catch a failed climb), refined while
    # still below it; where contact was entered under the pulse (a start in contact goes on by
    # the fourth order instead: test_a_scene_that_starts_in_contact_goes_on_by_the_fourth_order)
    under = dict(started, start_void_margin=2.0 * span)
    for error in (0.1 * tol, 0.1 * tol / REFINE**2, 8 * tol):
        assert start_config(contact, half, dict(under, step_error=error), scene) == contact
        assert start_config(contact, quarter, dict(under, step_error=error), scene) == half


def test_the_driver_judges_a_solve_in_contact_at_half_its_step(scene):
    """`solve_with_policy(objective=...)`: a fixed step with contact whose voids reached the
    cutoff (here at its start) and passed the other checks is solved again from the same start at half its step, and the
    Richardson-scaled change of the caller's objective goes into the health as "step_error".
    Within the tolerance the whole step stands; over it the same start is also solved at a
    quarter of the step, and the half- or the quarter-step solve stands in its place (not
    solved again) as `policy.after_quarter_step` says; else Dopri8 (not judged: an adaptive
    solve)."""
    from design_engine.solve.policy import STEP_ERROR_TOLERANCE

    tol = STEP_ERROR_TOLERANCE
    span = float(scene.material.contact_cutoff - scene.material.contact_min)
    contact = VERLET_CONTACT
    half, quarter = refined(contact), refined(refined(contact))
    started = healthy(scene, void_margin=0.5 * span, start_void_margin=0.5 * span)

    def objective(*moves):
        """J of "result 1" = 1, each next result's J moved by the given estimate (x tol) from
        the one before (4/3 of the relative change)."""
        values = [1.0]
        for m in moves:
            values.append(values[-1] * (1.0 + 0.75 * m * tol))
        return lambda result: values[int(result.split()[1]) - 1]

    def run(moves, *answers):
        solve = Script(*answers)
        return solve, solve_with_policy(scene, contact, solve, objective=objective(*moves))

    solve, out = run([0.5], started, started)
    assert solve.calls == [contact, half] and out.result == "result 1" and out.resolves == ()
    assert out.health["step_error"] == pytest.approx(0.5 * tol)
    # over the tolerance: judged at a quarter; the half's own estimate passes, the half stands
    solve, out = run([2.0, 0.5], started, started, started)
    assert solve.calls == [contact, half, quarter] and out.result == "result 2"
    assert out.config == half and "stands" in out.resolves[0] and len(out.resolves) == 1
    assert out.health["step_error"] == pytest.approx(0.5 * tol)
    # the half's estimate over it, the changes 4:1: the quarter stands on that pair
    solve, out = run([6.0, 1.5], started, started, started)
    assert solve.calls == [contact, half, quarter] and out.result == "result 3"
    assert out.config == quarter and out.health["step_error"] == pytest.approx(1.5 / 4 * tol)
    # changes that grow (not converging): Dopri8, solved and not judged
    solve, out = run([3.0, 3.0], started, started, started, started)
    assert solve.calls == [contact, half, quarter, contact_config()]
    assert out.result == "result 4" and out.config == contact_config()
    assert "Dopri8" in out.resolves[0] and "(the changes 1.0:1)" in out.resolves[0]
    # not predicted to pass at a quarter: Dopri8 at once
    solve, out = run([20.0], started, started, started)
    assert solve.calls == [contact, half, contact_config()] and out.result == "result 3"
    # a half-step solve that fails leaves the result untrusted at its step: inf, then Dopri8
    solve, out = run([], started, SimulationError("the half-step solve diverged"), started)
    assert out.config == contact_config() and "inf" in out.resolves[0]
    # one that entered contact under the pulse is judged so too; one whose voids stayed clear
    # of the cutoff, or that drifted, is not
    solve, out = run([0.5], *[healthy(scene, void_margin=0.5 * span,
                                      start_void_margin=2 * span)] * 2)
    assert solve.calls == [contact, half] and out.health["step_error"] == pytest.approx(0.5 * tol)
    solve, _ = run([0.0], healthy(scene))
    assert solve.calls == [contact]
    solve, _ = run([0.0], dict(started, energy_error=1.0), started)
    assert solve.calls == [contact, contact_config()]


def test_a_fourth_order_solve_in_contact_is_judged_at_a_coarser_step(scene):
    """The fourth-order step (`FixedStepVerlet(order=4)`, the policy's choice where the pulse
    starts in contact) is judged by the same start solved at COARSE x its step
    (`policy.check_config`), its estimate the change of the objective over COARSE^3 - 1
    (`policy.coarse_step_error`). Within the tolerance it stands; over it, where halving is
    predicted to pass (the estimate x 1/8 within half the tolerance) or the coarser solve
    failed, the same start is solved at half the step, which stands when its error by the pair
    (the change over 2^3 - 1, `policy.half_step_pair_error`) passes; else Dopri8. A refined step
    is not halved again. The Verlet estimate's wording and arithmetic are unchanged
    (`relative_step_error`'s default is 4/3 of the change)."""
    from design_engine.solve.policy import (COARSE, COARSE_CHECK_ORDER, STEP_ERROR_TOLERANCE,
                                            after_coarse_check, check_config,
                                            coarse_step_error, half_step_pair_error,
                                            next_config, relative_step_error)

    tol = STEP_ERROR_TOLERANCE
    span = float(scene.material.contact_cutoff - scene.material.contact_min)
    fourth = with_contact(VERLET)
    assert fourth.solver.order == 4
    coarse, half = check_config(fourth), refined(fourth)
    assert check_config(VERLET_CONTACT) == refined(VERLET_CONTACT)
    assert coarse.solver.max_dt == pytest.approx(COARSE * fourth.solver.max_dt)
    assert coarse.solver.order == 4 and not coarse.solver.refined
    assert relative_step_error(1.0, 1.0 + 3e-4) == pytest.approx(4e-4)
    assert coarse_step_error(2.0, 2.0 + 2 * 4.75e-4) == pytest.approx(
        4.75e-4 / (COARSE**COARSE_CHECK_ORDER - 1))
    assert half_step_pair_error(2.0, 2.0 + 2 * 7e-4) == pytest.approx(1e-4)
    assert after_coarse_check(4 * tol, fourth) and not after_coarse_check(4.1 * tol, fourth)
    assert after_coarse_check(float("inf"), fourth)
    assert not after_coarse_check(2 * tol, half)
    started = healthy(scene, void_margin=0.5 * span, start_void_margin=0.5 * span)
    nxt, why = next_config(fourth, dict(started, step_error=2 * tol), scene)
    assert nxt == contact_config() and f"at {COARSE:g} x the step" in why

    def run(values, *answers):
        """The driver on the fourth-order step; `values`: J of each result in turn."""
        solve = Script(*answers)
        out = solve_with_policy(scene, fourth, solve, objective=lambda r: values[
            int(r.split()[1]) - 1])
        return solve, out

    growth = COARSE**COARSE_CHECK_ORDER - 1
    solve, out = run([1.0, 1.0 + 0.5 * tol * growth], started, started)
    assert solve.calls == [fourth, coarse] and out.result == "result 1" and out.resolves == ()
    assert out.health["step_error"] == pytest.approx(0.5 * tol)
    # over the tolerance, halving predicted to pass: the half stands on its pair's error
    solve, out = run([1.0, 1.0 + 2 * tol * growth, 1.0 + 0.5 * tol * 7], started, started,
                     started)
    assert solve.calls == [fourth, coarse, half] and out.result == "result 3"
    assert out.config == half and "stands" in out.resolves[0]
    assert out.health["step_error"] == pytest.approx(0.5 * tol, rel=1e-3)
    # the pair's error over the tolerance too: Dopri8, not judged
    solve, out = run([1.0, 1.0 + 2 * tol * growth, 1.0 + 2 * tol * 7, 1.0], started, started,
                     started, started)
    assert solve.calls == [fourth, coarse, half, contact_config()]
    assert "Dopri8" in out.resolves[0] and "by the pair" in out.resolves[0]
    # not predicted to pass at half the step: Dopri8 at once
    solve, out = run([1.0, 1.0 + 5 * tol * growth, 1.0], started, started, started)
    assert solve.calls == [fourth, coarse, contact_config()]
    # the coarser solve failed (beyond the composition's stability): the half is tried
    solve, out = run([1.0, None, 1.0 + 0.5 * tol * 7], started,
                     SimulationError("the coarser solve diverged"), started)
    assert solve.calls == [fourth, coarse, half] and out.config == half


def test_a_fourth_order_step_above_verlets_is_judged_at_verlets_and_that_solve_may_stand(scene):
    """The fourth order of a static pre-compression in contact takes STATIC_CONTACT_STEP x
    Verlet's step, marked `finer_check`: it is judged by the same start at 1 / COARSE of its
    step (`policy.check_config`, marked refined), its estimate the change over
    1 - COARSE^-3. Within the tolerance it stands; over it, the finer solve stands in its
    place when its own error by the pair (the change over COARSE^3 - 1) passes, with no
    half-step solve (`policy.after_coarse_check`); else Dopri8. A finer solve that stood is
    climbed back from at the next evaluation (`policy.start_config`), to the marked step."""
    from design_engine.solve.policy import (COARSE, COARSE_CHECK_ORDER, STATIC_CONTACT_STEP,
                                            STEP_ERROR_TOLERANCE, after_coarse_check,
                                            check_config, check_ratio)

    tol = STEP_ERROR_TOLERANCE
    span = float(scene.material.contact_cutoff - scene.material.contact_min)
    fourth = with_contact(VERLET)
    marked = dataclasses.replace(fourth, solver=dataclasses.replace(
        fourth.solver, max_dt=STATIC_CONTACT_STEP * VERLET.solver.max_dt, finer_check=True))
    fine = check_config(marked)
    assert check_ratio(marked) == pytest.approx(1 / COARSE) and check_ratio(fourth) == COARSE
    assert fine.solver.max_dt == pytest.approx(VERLET.solver.max_dt)
    assert fine.solver.refined and fine.solver.order == 4 and fine.solver.finer_check
    assert not after_coarse_check(float("inf"), marked)
    # the mark changes no program: both steps' programs are those of the unmarked scheme
    assert marked.solver.summary()["finer_check"] and "finer_check" not in fourth.solver.summary()
    started = healthy(scene, void_margin=0.5 * span, start_void_margin=0.5 * span)
    shrink = 1 - COARSE**-COARSE_CHECK_ORDER  # the coarse solve's error over the change
    growth = COARSE**COARSE_CHECK_ORDER - 1  # the finer solve's

    def run(values, *answers):
        solve = Script(*answers)
        out = solve_with_policy(scene, marked, solve, objective=lambda r: values[
            int(r.split()[1]) - 1])
        return solve, out

    solve, out = run([1.0, 1.0 + 0.5 * tol * shrink], started, started)
    assert solve.calls == [marked, fine] and out.result == "result 1" and out.resolves == ()
    assert out.health["step_error"] == pytest.approx(0.5 * tol, rel=1e-6)
    # over the tolerance, the finer solve's own error within it: the finer solve stands
    change = 2 * tol * shrink
    assert change / growth < tol
    solve, out = run([1.0, 1.0 + change], started, started)
    assert solve.calls == [marked, fine] and out.result == "result 2" and out.config == fine
    assert "0.67 x the step" in out.resolves[0] and "finer solve" in out.resolves[0]
    assert out.health["step_error"] == pytest.approx(change / growth, rel=1e-3)
    # the finer solve's error over it too: Dopri8
    solve, out = run([1.0, 1.0 + 2 * tol * growth, 1.0], started, started, started)
    assert solve.calls == [marked, fine, contact_config()]
    assert "finer solve's error by the pair" in out.resolves[0]
    # the finer solve failed: the step's estimate is inf, and Dopri8 judges
    solve, out = run([1.0, None, 1.0], started, SimulationError("diverged"), started)
    assert solve.calls == [marked, fine, contact_config()]
    # the next evaluation climbs back from the finer step to the marked one
    up = start_config(marked, fine, dict(started, step_error=0.5 * tol), scene)
    assert up == marked


def test_a_run_in_contact_goes_on_by_the_fourth_order(scene):
    """`policy.start_config` after an evaluation in contact: the fourth order (`with_contact`)
    continues, after Dopri8 it gets its chance again at the choice's step, and a refined
    fourth order (its half stood) climbs back one halving an evaluation, whether the pulse
    started in contact or entered it."""
    span = float(scene.material.contact_cutoff - scene.material.contact_min)
    fourth = with_contact(VERLET)
    assert fourth.solver.order == 4 and fourth.solver.max_dt == VERLET.solver.max_dt
    assert not fourth.solver.refined and fourth.use_contact
    for start in (0.5 * span, 2.0 * span):
        health = healthy(scene, void_margin=0.5 * span, start_void_margin=start)
        assert start_config(VERLET, fourth, health, scene) == fourth
        assert start_config(VERLET, contact_config(), health, scene) == fourth
        assert start_config(VERLET, refined(refined(fourth)), health, scene) == refined(fourth)
        assert start_config(VERLET, refined(fourth), health, scene) == fourth


class ByConfig:
    """A stand-in solve that may be called from several threads: answers each configuration
    with its own entry of `answers` (`[(config, health or exception)]`, each solved at most
    once) and records which thread solved it, as the solve ends."""

    def __init__(self, answers):
        self.answers, self.threads = answers, []

    def __call__(self, config):
        import threading

        k = next(k for k, (c, _) in enumerate(self.answers) if c == config)
        answer = self.answers[k][1]
        self.threads.append((k, threading.current_thread().name))
        if isinstance(answer, Exception):
            raise answer
        return f"result {k}", answer


def test_a_half_step_solve_started_ahead_changes_nothing_but_the_thread(scene):
    """`solve_with_policy(ahead=)`: when the previous evaluation's solve started in contact,
    the half-step solve that the check will most likely ask for starts on the executor beside
    the step's own solve. Where the policy then asks for that configuration (the step check,
    or a re-solve at half the step after a drift) it takes that solve, which ran on the other
    thread; where it does not (a drift beyond refining: Dopri8) the solve is waited for and
    dropped. Each outcome (result, configuration, reasons, health) equals the one without the
    executor, with the same solves but that dropped one, which the outcome counts as unused."""
    from concurrent.futures import ThreadPoolExecutor

    from design_engine.solve.policy import STEP_ERROR_TOLERANCE

    tol = STEP_ERROR_TOLERANCE
    span = float(scene.material.contact_cutoff - scene.material.contact_min)
    contact = VERLET_CONTACT
    half, quarter = refined(contact), refined(refined(contact))
    started = healthy(scene, void_margin=0.5 * span, start_void_margin=0.5 * span)
    drift = dict(started, energy_error=2 * ENERGY_TOLERANCE)  # refining predicted to pass
    cases = {  # answers, J of each answer in turn
        "stands": ([(contact, started), (half, started)], [1.0, 1.0 + 0.375 * tol]),
        "the half stands": ([(contact, started), (half, started), (quarter, started)],
                            [1.0, 1.0 + 1.5 * tol, 1.0 + 1.875 * tol]),
        "refined after a drift": ([(contact, drift), (half, started), (quarter, started)],
                                  [1.0, 1.0, 1.0 + 0.375 * tol]),
        "Dopri8 after a drift": ([(contact, dict(started, energy_error=1.0)), (half, started),
                                  (contact_config(), started)], [1.0, 1.0, 1.0]),
    }
    for case, (answers, values) in cases.items():
        def solve_with(ahead, solve, values=values):
            return solve_with_policy(scene, contact, solve, previous=lambda: (None, started),
                                     objective=lambda r: values[int(r.split()[1])],
                                     ahead=ahead)

        plain, alone = ByConfig(answers), None
        alone = solve_with(None, plain)
        with ThreadPoolExecutor(1, "ahead") as pool:
            both = ByConfig(answers)
            beside = solve_with(pool, both)
            solved = sorted(both.threads)  # every solve started ahead has ended
        assert (beside.result, beside.config, beside.resolves, beside.health) == \
            (alone.result, alone.config, alone.resolves, alone.health), case
        dropped = [1] if case == "Dopri8 after a drift" else []
        assert [k for k, _ in solved] == sorted([k for k, _ in plain.threads] + dropped), case
        assert (alone.unused_ahead, beside.unused_ahead) == (0, len(dropped)), case
        assert solved[1] == (1, "ahead_0"), case  # the half step, on the executor's thread
        assert all(name == "MainThread" for k, name in solved if k != 1), case
    assert beside.config == contact_config() and "Dopri8" in beside.resolves[0]


def test_the_step_is_differentiated_while_the_half_step_solve_that_judges_it_runs(scene):
    """`solve_with_policy(ahead=, finish=)`: where the half-step solve that will judge a step
    was started ahead and the previous evaluation's solve stood at the same step on its own
    check, the step's `finish` (an optimiser's reverse pass) runs while it is under way. Where
    the step stands, that early finish is the outcome's; where the half step stands instead, it
    is finished too and counts (the early finish wasted, never used); a finish that failed
    early counts as that solve's failure, as it does when taken late. A step climbing back
    from the half that stood before (contact entered under the pulse) is finished only once
    judged. Every outcome equals the one
    without the executor, which finishes the solve that stands alone."""
    from concurrent.futures import ThreadPoolExecutor

    from design_engine.solve.policy import CONTACT_SUBSTEPS_MAX, STEP_ERROR_TOLERANCE, with_substeps

    tol = STEP_ERROR_TOLERANCE
    span = float(scene.material.contact_cutoff - scene.material.contact_min)
    contact = VERLET_CONTACT
    half, quarter = refined(contact), refined(refined(contact))
    started = healthy(scene, void_margin=0.5 * span, start_void_margin=0.5 * span)
    substepped = with_substeps(contact, CONTACT_SUBSTEPS_MAX)
    judged = [(contact, started), (half, started), (quarter, started)]
    # the previous evaluation's configuration, the answers, J of each answer in turn, results
    # whose finish fails, the results finished with the executor and without it
    cases = {
        "stands": (contact, judged[:2], [1.0, 1.0 + 0.375 * tol], (), ["result 0"],
                   ["result 0"]),
        "the half stands": (contact, judged, [1.0, 1.0 + 1.5 * tol, 1.0 + 1.875 * tol], (),
                            ["result 0", "result 1"], ["result 1"]),
        "its finish fails": (contact, judged[:2] + [(substepped, healthy(scene))],
                             [1.0, 1.0, 1.0], ("result 0",), ["result 0", "result 2"],
                             ["result 0", "result 2"]),
        "a climb": (half, judged, [1.0, 1.0 + 1.5 * tol, 1.0 + 1.875 * tol], (), ["result 1"],
                    ["result 1"]),
    }
    for case, (last, answers, values, failing, with_pool, without) in cases.items():
        def solve_with(ahead, solve, finished, last=last, values=values, failing=failing):
            def finish(result):
                finished.append(result)
                if result in failing:
                    raise SimulationError("non-finite gradient")
                return f"finished {result}"

            return solve_with_policy(scene, contact, solve,
                                     previous=lambda: (last, dict(  # entered under the pulse
                                         started, start_void_margin=2.0 * span,
                                         step_error=0.5 * tol)),
                                     objective=lambda r: values[int(r.split()[1])],
                                     finish=finish, ahead=ahead)

        late, early = [], []
        alone = solve_with(None, ByConfig(answers), late)
        with ThreadPoolExecutor(1, "ahead") as pool:
            beside = solve_with(pool, ByConfig(answers), early)
        assert (beside.result, beside.config, beside.resolves, beside.health) == \
            (alone.result, alone.config, alone.resolves, alone.health), case
        assert (early, late) == (with_pool, without), case
        if case == "its finish fails":
            assert "non-finite gradient" in beside.resolves[0] and beside.config == substepped
