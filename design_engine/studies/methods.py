"""The solver/model configurations compared by the speed-accuracy studies, by name.

A method is a `SolverConfig` plus the family it is charted in. Tolerances are on positions (mm)
and velocities (mm/s), as the reference's (spec 6.5).
"""

from dataclasses import dataclass

import diffrax

from design_engine.solve.fixed_step import FixedStepVerlet, is_fixed_step
from design_engine.solve.implicit_step import ImplicitNewmark
from design_engine.solve.simulate import SolverConfig

SPEC_TOL = (1e-8, 1e-4)


@dataclass(frozen=True)
class Method:
    """One point (or curve member) of a work-precision chart."""

    name: str
    family: str
    config: SolverConfig


def _adaptive(solver, tag, rtol, atol, **kw) -> Method:
    return Method(f"{tag} rtol={rtol:g} atol={atol:g}", tag, SolverConfig(solver=solver, rtol=rtol,
                                                                          atol=atol, **kw))


def reference_method() -> Method:
    """Tight-tolerance 8th-order solution every other method is measured against."""
    return _adaptive(diffrax.Dopri8(), "Dopri8", 1e-11, 1e-9, max_steps=400_000)


def baseline_method() -> Method:
    """Our engine configured as the published reference code: Dopri5, spec tolerances,
    continuous (backsolve) adjoint, float64, full model."""
    return Method("baseline Dopri5 spec-tol backsolve", "baseline",
                  SolverConfig(solver=diffrax.Dopri5(), rtol=SPEC_TOL[0], atol=SPEC_TOL[1],
                               adjoint=diffrax.BacksolveAdjoint()))


def verlet(max_dt: float, **kw) -> Method:
    tag = "Verlet" + ("-f32" if kw.get("dtype") == "float32" else "")
    for k in ("linearized", "use_contact"):
        if k in kw:
            tag += {"linearized": "-linear", "use_contact": "-nocontact"}[k]
    return Method(f"{tag} dt={max_dt:g}ms", tag, SolverConfig(solver=FixedStepVerlet(max_dt=max_dt),
                                                               **kw))


def newmark(max_dt: float, iterations: int, **kw) -> Method:
    tag = "Newmark-implicit" + ("-f32" if kw.get("dtype") == "float32" else "")
    return Method(f"{tag} dt={max_dt:g}ms x{iterations}", tag,
                  SolverConfig(solver=ImplicitNewmark(max_dt=max_dt, iterations=iterations), **kw))


def study_methods(quick: bool = False) -> list[Method]:
    """Methods of the work-precision study (`quick`: a reduced set for smoke runs)."""
    if quick:
        return [_adaptive(diffrax.Dopri5(), "Dopri5", *SPEC_TOL), verlet(0.04), verlet(0.02)]
    out = [_adaptive(diffrax.Tsit5(), "Tsit5", *t) for t in (SPEC_TOL, (1e-6, 1e-3))]
    out += [_adaptive(diffrax.Dopri5(), "Dopri5", *t) for t in (SPEC_TOL, (1e-6, 1e-3), (1e-5, 1e-2))]
    out += [_adaptive(diffrax.Dopri8(), "Dopri8", *SPEC_TOL)]
    out.append(baseline_method())
    out.append(Method("Dopri5 spec-tol checkpoints=64", "Dopri5-checkpoints",
                      SolverConfig(adjoint=diffrax.RecursiveCheckpointAdjoint(checkpoints=64))))
    out += [_adaptive(diffrax.Dopri5(), "Dopri5-f32", 1e-6, 1e-2, dtype="float32")]
    out += [verlet(dt) for dt in (0.04, 0.02, 0.01)]
    out += [verlet(0.02, dtype="float32")]
    out += [verlet(0.02, use_contact=False), verlet(0.02, linearized=True)]
    # implicit trapezoidal Newmark, chord iterations on the factored initial stiffness: 1x, 2x
    # and 3-4x the default Verlet step (the last two are expected to fail: see implicit_step)
    out += [newmark(dt, 3) for dt in (0.04, 0.08)] + [newmark(0.08, 3, dtype="float32")]
    out += [newmark(0.12, 4), newmark(0.16, 6)]
    # diffrax's implicit ESDIRK last: a dense Jacobian and LU per Newton step make it the
    # slowest by far here (run only with --implicit)
    out += [_adaptive(diffrax.Kvaerno5(), "Kvaerno5 (implicit)", 1e-4, 1e-2)]
    return out


def rhs_evaluations(config: SolverConfig, num_steps: int) -> int:
    """Right-hand-side (force) evaluations of a solve with `num_steps` steps (attempted)."""
    solver = config.solver
    if is_fixed_step(solver):
        return solver.force_evaluations(num_steps)
    tableau = getattr(solver, "tableau", None)
    if tableau is None:  # implicit solvers: stages (Newton iterations not counted)
        return -1
    stages = len(tableau.c) + 1
    return num_steps * (stages - (1 if tableau.fsal else 0)) + 1
