"""The fixed-step Verlet schemes on a system whose motion is known independently."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

from design_engine.solve.fixed_step import SUZUKI_4, FixedStepVerlet, step_grid

STIFFNESS = np.array([1.0, 4.0])
DAMPING = np.array([0.05, 0.1])
MASS = np.array([1.0, 2.0])
Q0, V0 = np.array([1.0, 0.5]), np.array([0.0, -0.3])
TS = np.linspace(0.0, 10.0, 11)


def _forcing(t):
    return np.array([1.0, 0.0]) * np.sin(t)  # time-dependent, as a prescribed motion's


def _fixed_step(max_dt, order, dtype=jnp.float64, ts=TS, hlo=None):
    """The scheme's (q, v) at `ts` (from t0 = 0); `hlo`: a list that gets the program's text.
    Importing design_engine enables float64."""
    stiffness, forcing = jnp.asarray(STIFFNESS, dtype), jnp.asarray([1.0, 0.0], dtype)

    def force(q, t):
        return (-stiffness * q + forcing * jnp.sin(t),
                (0.5 * jnp.sum(stiffness * q * q), jnp.zeros((), dtype)))

    method = FixedStepVerlet(max_dt=max_dt, order=order)
    integrate = method.make_integrator(step_grid(ts, max_dt), None, None, 2)
    args = (jnp.asarray(1.0 / MASS, dtype), jnp.asarray(DAMPING, dtype),
            (jnp.asarray(Q0, dtype), jnp.asarray(V0, dtype)), jnp.asarray(ts, dtype))
    if hlo is not None:
        hlo.append(jax.jit(lambda *a: integrate(force, *a)).lower(*args).as_text())
    qs, vs, converged, _ = integrate(force, *args)
    assert bool(converged) and qs.dtype == dtype
    return np.asarray(qs), np.asarray(vs)


def _reference(ts=TS):
    def rhs(t, y):
        q, v = y[:2], y[2:]
        return np.concatenate([v, (-STIFFNESS * q - DAMPING * v + _forcing(t)) / MASS])

    sol = solve_ivp(rhs, (0.0, ts[-1]), np.concatenate([Q0, V0]), method="DOP853", t_eval=ts,
                    rtol=1e-13, atol=1e-13)
    return sol.y[:2].T, sol.y[2:].T


@pytest.mark.parametrize("order", [2, 4])
def test_each_halving_of_the_step_divides_the_error_by_two_to_the_order(order):
    # damped, forced and with two frequencies: the damping's implicit half kick and the
    # time-dependent force must keep the composition symmetric, else it falls to second order
    q_ref, v_ref = _reference()
    errors = []
    for dt in (0.2, 0.1, 0.05):
        qs, vs = _fixed_step(dt, order)
        errors.append(max(np.max(np.abs(qs - q_ref)), np.max(np.abs(vs - v_ref))))
    ratios = np.array(errors[:-1]) / np.array(errors[1:])
    assert ratios == pytest.approx(2.0 ** order, rel=0.1), errors
    assert errors[-1] < (1e-6 if order == 4 else 2e-3)


def test_samples_that_start_late_are_reached_in_one_loop_of_whole_intervals():
    # the pulse scenes sample from the window's start on: the steps before the first sample are
    # whole intervals of the samples' step count, taken by the same loop as the rest, so the
    # step is in the program once (a loop of their own was a second copy XLA compiled again)
    ts = np.linspace(2.3, 10.0, 12)
    grid = step_grid(ts, 0.1)
    assert grid.n_sub == 7 and grid.n_pre == 28  # 23 steps of at most 0.1, rounded up to 4 x 7
    assert grid.n_steps == grid.n_pre + 11 * grid.n_sub
    q_ref, v_ref = _reference(ts)
    hlo, errors = [], []
    for dt in (0.1, 0.05):
        qs, vs = _fixed_step(dt, 2, ts=ts, hlo=hlo)
        errors.append(max(np.max(np.abs(qs - q_ref)), np.max(np.abs(vs - v_ref))))
    assert errors[0] / errors[1] == pytest.approx(4.0, rel=0.1), errors  # second order
    # two loops (the intervals, the steps within one); the sine of the force is in the step,
    # and once more in the force at the start
    assert hlo[0].count("stablehlo.while") == 2 and hlo[0].count("stablehlo.sine") == 2


def test_the_fourth_order_step_is_five_verlet_steps_that_span_it():
    assert sum(SUZUKI_4) == pytest.approx(1.0, abs=1e-15)
    assert SUZUKI_4 == SUZUKI_4[::-1]  # symmetric
    assert FixedStepVerlet(max_dt=0.01, order=4).force_evaluations(10) == 51
    assert FixedStepVerlet(max_dt=0.01, order=4).summary()["order"] == 4
    assert "order" not in FixedStepVerlet(max_dt=0.01).summary()
    with pytest.raises(ValueError, match="order must be 2 or 4"):
        FixedStepVerlet(order=3)


def test_the_fourth_order_step_runs_in_float32():
    # the composition's fractions enter as Python floats: a float32 solve stays float32 (a
    # numpy float64 start time once promoted its carry, and the scan refused it)
    q32, _ = _fixed_step(0.05, 4, jnp.float32)
    q64, _ = _fixed_step(0.05, 4)
    # 1000 sub-steps of float32 rounding (measured 1.1e-5 on amplitudes up to 3.1)
    assert np.max(np.abs(q32 - q64)) < 1e-4


def test_steps_on_one_grid_share_one_program_and_its_result():
    """A fixed step's program depends on its step grid, not on the step asked for nor on the
    policy's mark of a refined step (`run.compile_key`): two steps that give one grid get one
    program, whose result is the one a program built for the other step gives; another grid,
    another program."""
    import dataclasses

    from design_engine.physics.scenes import build_scene
    from design_engine.solve.run import compiled_simulator
    from design_engine.solve.simulate import SolverConfig, make_simulator

    scene = build_scene("focusing-24x16", nx=4, ny=3, amplitude_m=2e-3)
    ts = np.asarray(scene.sample_times)
    interval = float(np.max(np.diff(ts)))
    on_grid = [interval / 10.0, interval / 9.6]  # both 10 steps a sample interval
    assert {step_grid(ts, dt).n_sub for dt in on_grid} == {10}
    config = SolverConfig(solver=FixedStepVerlet(max_dt=on_grid[0]), use_contact=False)
    other = dataclasses.replace(config, solver=FixedStepVerlet(max_dt=on_grid[1], refined=True))
    program = compiled_simulator(scene, config)
    assert compiled_simulator(scene, other) is program
    assert compiled_simulator(scene, dataclasses.replace(
        config, solver=FixedStepVerlet(max_dt=interval / 11.0))) is not program
    args = (jnp.asarray(scene.design), scene.material, scene.loading, jnp.asarray(ts))
    own = jax.jit(make_simulator(scene.lattice, scene.supports, other, ts, model=scene.model))
    np.testing.assert_array_equal(np.asarray(program(*args).q), np.asarray(own(*args).q))
