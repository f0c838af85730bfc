"""Bookkeeping of the speed-accuracy studies (selection rule, RHS counts)."""

import diffrax

from design_engine.fixed_step import FixedStepVerlet
from design_engine.implicit_step import ImplicitNewmark
from design_engine.simulate import SolverConfig
from design_engine.studies.methods import rhs_evaluations
from design_engine.studies.work_precision import acceptable, fastest_acceptable


def _row(t, j=1e-4, g=1e-3, cos=0.99999, **kw):
    return {"family": "x", "value_and_grad_s": t, "J_rel_err": j, "grad_rel_err": g,
            "grad_cosine": cos, **kw}


def test_selection_takes_the_fastest_method_acceptable_on_every_scene():
    results = {"scenes": {
        "a": {"methods": {"fast-but-wrong": _row(0.1, j=2e-2), "slow": _row(9.0), "mid": _row(1.0),
                          "mid-fails-b": _row(0.5)}},
        "b": {"methods": {"fast-but-wrong": _row(0.1), "slow": _row(9.0), "mid": _row(1.5),
                          "mid-fails-b": {"family": "x", "error": "SimulationError: diverged"}}},
    }}
    assert not acceptable(results["scenes"]["a"]["methods"]["fast-but-wrong"])
    assert not acceptable(_row(1.0, cos=0.99))
    assert fastest_acceptable(results)[0] == "mid"


def test_rhs_evaluation_counts():
    assert rhs_evaluations(SolverConfig(), 100) == 100 * 6 + 1  # Dopri5: 7 stages, FSAL
    assert rhs_evaluations(SolverConfig(solver=diffrax.Tsit5()), 10) == 61
    assert rhs_evaluations(SolverConfig(solver=FixedStepVerlet(max_dt=0.01)), 500) == 501
    # one force evaluation per chord iteration, plus the initial acceleration
    assert rhs_evaluations(SolverConfig(solver=ImplicitNewmark(iterations=3)), 200) == 601
