"""Run-time step counts of the fixed-step solves: the capacity buckets, one compiled program for
every step of a bucket, and the skipped steps of a program's capacity left out of the result
and its gradient."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from design_engine.physics.scenes import build_scene
from design_engine.solve.fixed_step import FixedStepVerlet, capacity, step_capacity, step_grid
from design_engine.solve.objectives import region_energy
from design_engine.solve.policy import refined
from design_engine.solve.simulate import SolverConfig, fixed_steps, make_simulator, program_key


@pytest.fixture(scope="module")
def scene():
    return build_scene("focusing-24x16", nx=6, ny=4, amplitude_m=2e-3)


@pytest.fixture(scope="module")
def ts():
    """Sample times through the start of the pulse, 0.2 ms apart."""
    return np.linspace(0.0, 6.0, 31)


def test_capacity_holds_the_count_and_leaves_at_most_a_third_unused():
    assert capacity(0) == 0
    caps = [capacity(n) for n in range(1, 2000)]
    assert all(c >= n for n, c in zip(range(1, 2000), caps))
    assert all(c - n <= c / 3 for n, c in zip(range(1, 2000), caps))
    assert caps == sorted(caps)  # a larger count never gets a smaller program
    assert len(set(caps)) <= 2 * 11 + 1  # two buckets per doubling


def test_steps_of_one_bucket_share_a_program_and_the_refined_flag_is_no_part_of_it(scene, ts):
    dt = 0.021
    base = SolverConfig(solver=FixedStepVerlet(max_dt=dt))
    near = SolverConfig(solver=FixedStepVerlet(max_dt=0.97 * dt))
    n, m = step_grid(ts, dt).n_sub, step_grid(ts, 0.97 * dt).n_sub
    assert capacity(n) == capacity(m)  # the premise: one bucket
    assert program_key(base, ts) == program_key(near, ts)
    half = refined(base)
    same = capacity(step_grid(ts, half.solver.max_dt).n_sub) == capacity(n)
    assert (program_key(half, ts) == program_key(base, ts)) == same
    assert program_key(base, ts) != program_key(SolverConfig(solver=FixedStepVerlet(
        max_dt=dt), dtype="float32"), ts)


def _energy_program(scene, config, ts, grad: bool = True):
    """Jitted `(x, steps) -> ((target energy, steps taken), d energy / dx)` (or without the
    gradient)."""
    sim = make_simulator(scene.lattice, scene.supports, config, ts)
    ids = np.asarray(next(iter(scene.targets.values())))

    def f(x, steps):
        sol = sim(x, scene.material, scene.loading, jnp.asarray(ts), steps=steps)
        return region_energy(sol, ids), sol.num_steps

    return jax.jit(jax.value_and_grad(f, has_aux=True) if grad else f)


def test_a_program_with_room_for_more_steps_gives_the_result_of_the_exact_count(scene, ts):
    # the program built for a small step (capacity 12 per interval) runs a larger step's 4
    # steps per interval: the steps it has room for beyond the count are skipped, so the value
    # and gradient are those of the program built for exactly that count
    small, large = 0.017, 0.05
    cap_small = step_capacity(step_grid(ts, small))
    cap_large = step_capacity(step_grid(ts, large))
    assert cap_small.n_sub > step_grid(ts, large).n_sub == cap_large.n_sub
    config = SolverConfig(solver=FixedStepVerlet(max_dt=large))
    roomy = _energy_program(scene, SolverConfig(solver=FixedStepVerlet(max_dt=small)), ts)
    exact = _energy_program(scene, config, ts)
    x = jnp.asarray(scene.design)
    steps = fixed_steps(config, ts)
    (j1, n1), g1 = roomy(x, steps)
    (j2, n2), g2 = exact(x, steps)
    assert int(n1) == int(n2) == step_grid(ts, large).n_steps
    np.testing.assert_allclose(float(j1), float(j2), rtol=1e-13)
    np.testing.assert_allclose(np.asarray(g1), np.asarray(g2), rtol=1e-10,
                               atol=1e-12 * float(jnp.max(jnp.abs(g2))))
    # and the step makes a difference: the same program at its own step gives another value
    (j3, _), _ = roomy(x, fixed_steps(SolverConfig(solver=FixedStepVerlet(max_dt=small)), ts))
    assert abs(float(j3) - float(j1)) > 1e-9 * abs(float(j1))


def test_the_step_before_the_first_sample_is_a_run_time_count_too(scene):
    # sample times that start after t = 0: the steps up to the first sample are counted too
    ts = np.linspace(0.5, 6.0, 12)
    a, b = 0.05, 0.043
    assert step_grid(ts, a).n_pre != step_grid(ts, b).n_pre
    assert program_key(SolverConfig(solver=FixedStepVerlet(max_dt=a)), ts) == program_key(
        SolverConfig(solver=FixedStepVerlet(max_dt=b)), ts)
    shared = _energy_program(scene, SolverConfig(solver=FixedStepVerlet(max_dt=a)), ts, False)
    own = _energy_program(scene, SolverConfig(solver=FixedStepVerlet(max_dt=b)), ts, False)
    steps = fixed_steps(SolverConfig(solver=FixedStepVerlet(max_dt=b)), ts)
    x = jnp.asarray(scene.design)
    j1, n1 = shared(x, steps)
    j2, n2 = own(x, steps)
    assert int(n1) == int(n2) == step_grid(ts, b).n_steps
    np.testing.assert_allclose(float(j1), float(j2), rtol=1e-13)
