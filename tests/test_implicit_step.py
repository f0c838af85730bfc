"""Implicit Newmark with chord iterations: the banded factorisation, stability above the explicit
limit, accuracy against the adaptive reference, gradients, and reported non-convergence."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from design_engine.physics.dynamics import make_full_state
from design_engine.physics.energy import bond_geometry, kinetic_energy, make_energy
from design_engine.physics.geometry import block_geometry
from design_engine.physics.loading import Loading
from design_engine.physics.scenes import build_scene
from design_engine.solve import implicit_step as im
from design_engine.solve.fixed_step import FixedStepVerlet
from design_engine.solve.implicit_step import ImplicitNewmark
from design_engine.solve.policy import max_angular_frequency
from design_engine.solve.run import simulate_scene
from design_engine.solve.simulate import (SimulationError, SolverConfig, check_solution,
                                          make_simulator)
from gradcheck import directional_check


@pytest.fixture(scope="module")
def small():
    return build_scene("focusing-24x16", nx=8, ny=6, amplitude_m=2e-3)


@pytest.fixture(scope="module")
def omega(small):
    """omega_max (rad/ms) of the small scene, measured once (each call traces the estimator)."""
    return max_angular_frequency(small)


@pytest.fixture(scope="module")
def verlet_dt(omega):
    """The default Verlet step of the small scene: 0.6 x the stability limit 2 / omega_max, ms."""
    return 0.6 * 2.0 / omega


def test_block_tridiagonal_factor_solves_a_banded_spd_system():
    rng = np.random.default_rng(1)
    n, b = 53, 6  # 53 is not a multiple of the block size: padding is exercised
    i, j = np.nonzero(np.abs(np.subtract.outer(np.arange(n), np.arange(n))) <= b)
    keep = rng.random(i.size) < 0.6
    a = np.zeros((n, n))
    a[i[keep], j[keep]] = rng.normal(size=keep.sum())
    a = a + a.T
    diagonal = np.abs(a).sum(axis=1) + 0.5  # diagonally dominant: S = A + diag is SPD
    layout = im.band_layout(np.stack([i[keep], j[keep]], 1), n)
    assert layout.bandwidth <= b and layout.n_blocks * layout.block >= n

    @jax.jit  # one program instead of hundreds of eager operations
    def banded_solve(a, diagonal, r):
        compressed = im.banded_stiffness(lambda v: a @ v, layout, jnp.float64)
        return im.solve(layout, im.factor(layout, compressed, diagonal), r)

    r = rng.normal(size=n)
    x = np.asarray(banded_solve(jnp.asarray(a), jnp.asarray(diagonal), jnp.asarray(r)))
    np.testing.assert_allclose(x, np.linalg.solve(a + np.diag(diagonal), r), rtol=1e-10, atol=1e-12)


def test_banded_assembly_reproduces_the_dense_stiffness_of_a_lattice(small):
    lat, sup = small.lattice, small.supports
    free = np.asarray(sup.free)
    layout = im.band_layout(im.free_dof_pairs(lat.bond_blocks, free, 3 * lat.n_blocks), free.size)
    bonds = bond_geometry(lat, block_geometry(lat, jnp.asarray(small.design)))
    energy, full = make_energy(lat), make_full_state(sup)

    def grad(qf):
        return jax.grad(lambda z: energy(full(z, jnp.asarray(0.0), Loading()), bonds,
                                         small.material))(qf)

    q0 = jnp.full(free.size, 0.01)  # away from rest, so geometric terms are present
    # jitted together: one program instead of the eager operations one by one
    dense, compressed = map(np.asarray, jax.jit(lambda q: (jax.jacfwd(grad)(q), im.banded_stiffness(
        lambda v: jax.jvp(grad, (q,), (v,))[1], layout, jnp.float64)))(q0))
    rows, cols = np.indices(dense.shape)
    band = np.abs(rows - cols) <= layout.bandwidth
    assert np.all(dense[~band] == 0.0)  # the bond graph gives the true bandwidth
    w = layout.probes
    np.testing.assert_allclose(compressed[rows[band], cols[band] % w], dense[band],
                               rtol=1e-12, atol=1e-9 * np.abs(dense).max())


def _free_vibration(scene, solver, t_end_ms: float, speed: float = 0.01):
    """Undamped free vibration from a random velocity (`speed` x a standard normal: 0.01 is
    10 mm/s, 10 rad/s); Hamiltonian [n_t] (mJ)."""
    lat, sup = scene.lattice, scene.supports
    n_free = sup.free.size
    v0 = speed * np.random.default_rng(0).normal(size=n_free)
    ts = np.linspace(0.0, t_end_ms, 101)
    config = SolverConfig(solver=solver)
    sim = jax.jit(make_simulator(lat, sup, config, ts))
    mat = scene.material.undamped()
    sol = check_solution(sim(jnp.asarray(scene.design), mat, Loading(amplitude=0.0),
                             jnp.asarray(ts), (jnp.zeros(n_free), jnp.asarray(v0))), config)
    bonds = bond_geometry(lat, block_geometry(lat, jnp.asarray(scene.design)))
    pot = jax.vmap(lambda q: make_energy(lat)(q, bonds, mat))(sol.q)
    return np.asarray(pot + kinetic_energy(sol.qdot, sol.mass, sol.inertia).sum(axis=1))


def test_implicit_step_is_stable_above_the_explicit_limit_and_keeps_the_energy(small, omega):
    # trapezoidal Newmark conserves the energy of a linear system exactly; the small geometric
    # nonlinearity leaves a bounded O(dt^2) deviation. Verlet at 3x its limit blows up
    deviation = {}
    for factor in (1.0, 3.0):
        ham = _free_vibration(small, ImplicitNewmark(max_dt=factor * 2.0 / omega, iterations=4),
                              20.0)
        deviation[factor] = np.max(np.abs(ham - ham[0])) / ham[0]
    assert deviation[3.0] < 2e-2 and deviation[1.0] < 3e-3
    assert deviation[3.0] / deviation[1.0] == pytest.approx(9.0, rel=0.5)  # second order
    with pytest.raises(SimulationError, match="non-finite|diverged"):
        _free_vibration(small, FixedStepVerlet(max_dt=3.0 * 2.0 / omega), 20.0)


def test_implicit_matches_the_adaptive_reference(small, verlet_dt):
    ref = simulate_scene(small, SolverConfig(rtol=1e-10, atol=1e-9)).metrics["target_ke_mean_J"]
    for dtype in ("float64", "float32"):
        got = simulate_scene(small, SolverConfig(solver=ImplicitNewmark(max_dt=verlet_dt),
                                                 dtype=dtype))
        assert got.metrics["target_ke_mean_J"] == pytest.approx(ref, rel=5e-3)
        assert got.metrics["solver"]["iterations_per_step"] == 3


def test_implicit_gradient_matches_finite_differences(small, verlet_dt):
    config = SolverConfig(solver=ImplicitNewmark(max_dt=verlet_dt))
    directional_check(small, config, h=1e-4, seed=5, rel=1e-5, one_program=True)


def test_unconverged_iterations_are_reported_not_returned(small, omega):
    # the free vibration of the test above at 3x the explicit limit (its compiled program),
    # started 30x faster (300 mm/s, 300 rad/s): the units rotate the stiff ligaments far enough
    # from their initial directions that the frozen-stiffness iteration does not converge
    # (before: the pulse scene at 2x the Verlet step, a program of its own)
    with pytest.raises(SimulationError, match="did not converge"):
        _free_vibration(small, ImplicitNewmark(max_dt=3.0 * 2.0 / omega, iterations=4), 20.0,
                        speed=0.3)


def test_bad_settings_are_refused():
    with pytest.raises(ValueError, match="iterations"):
        ImplicitNewmark(iterations=0)
    with pytest.raises(ValueError, match="max_dt"):
        ImplicitNewmark(max_dt=0.0)


def test_both_schemes_share_the_fixed_step_interface():
    import diffrax

    from design_engine.solve.fixed_step import is_fixed_step

    verlet, newmark = FixedStepVerlet(max_dt=0.01), ImplicitNewmark(iterations=4, tol=1e-5)
    assert is_fixed_step(verlet) and is_fixed_step(newmark) and not is_fixed_step(diffrax.Dopri5())
    assert verlet.stability_limited and not newmark.stability_limited
    assert newmark.with_max_dt(0.02) == ImplicitNewmark(max_dt=0.02, iterations=4, tol=1e-5)
    assert verlet.force_evaluations(10) == 11 and newmark.force_evaluations(10) == 41
    assert newmark.summary() == {"max_dt_s": 0.16e-3, "iterations_per_step": 4}
    assert "stability limit" in verlet.unstable_hint() and "1e-05" in newmark.unconverged_message()
