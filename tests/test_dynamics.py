"""Dynamics invariants: energy conservation, damping balance, modal frequency, failure reports."""

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from design_engine.physics.dynamics import dof_damping
from design_engine.physics.energy import bond_geometry, kinetic_energy, make_energy
from design_engine.physics.geometry import block_geometry
from design_engine.physics.lattice import periodic_design, quads
from design_engine.physics.loading import Loading, Supports
from design_engine.physics.material import Material
from design_engine.physics.modal import modal_analysis
from design_engine.physics.scenes import build_scene
from design_engine.solve.simulate import (SimulationError, SolverConfig, check_solution,
                                          make_simulator)


@functools.lru_cache(maxsize=None)
def _free_simulator(rtol: float, atol: float):
    """One jitted simulator of the free 6x6 lattice per tolerance, traced once for the file."""
    lat = quads(6, 6)
    return jax.jit(make_simulator(lat, Supports.from_rules(lat.n_blocks, {}),
                                  SolverConfig(rtol=rtol, atol=atol)))


def _free_lattice_run(damped: bool, t_end: float, rtol: float, atol: float):
    lat = quads(6, 6)
    x = jnp.asarray(periodic_design(lat, math.radians(25)))
    mat = Material.paper(lat)
    mat = mat if damped else mat.undamped()
    rng = np.random.default_rng(0)
    v0 = np.column_stack([rng.uniform(-0.2, 0.2, (lat.n_blocks, 2)),  # 200 mm/s in mm/ms
                          rng.uniform(-0.02, 0.02, lat.n_blocks)]).reshape(-1)  # 20 rad/s
    sim = _free_simulator(rtol, atol)
    ts = jnp.linspace(0.0, t_end, 501)
    sol = check_solution(sim(x, mat, Loading(amplitude=0.0), ts,
                             (jnp.zeros(3 * lat.n_blocks), jnp.asarray(v0))), SolverConfig())
    g = block_geometry(lat, x)
    energy = make_energy(lat)
    pot = jax.vmap(lambda q: energy(q, bond_geometry(lat, g), mat))(sol.q)
    ham = np.asarray(pot + kinetic_energy(sol.qdot, sol.mass, sol.inertia).sum(axis=1))
    return lat, mat, sol, ham


def test_energy_is_conserved_without_damping():
    # 20 ms (the damping test's record, one compiled program for both; was 50 ms): measured
    # drift 8.8e-9 (2.2e-8 over 50 ms), two orders below the bound, which rounding on another
    # CPU cannot approach; a solve at rtol = atol = 1e-6 drifts 1.5e-4 and fails it
    _, _, _, ham = _free_lattice_run(False, 20.0, 1e-10, 1e-10)
    drift = np.max(np.abs(ham - ham[0])) / ham[0]
    assert drift < 1e-6, drift


def test_damping_dissipates_exactly_the_viscous_work():
    lat, mat, sol, ham = _free_lattice_run(True, 20.0, 1e-10, 1e-10)
    c = np.asarray(dof_damping(lat.n_blocks, mat)).reshape(lat.n_blocks, 3)
    power = np.sum(c[None] * np.asarray(sol.qdot) ** 2, axis=(1, 2))
    ts = np.asarray(sol.ts)
    work = np.concatenate([[0.0], np.cumsum(0.5 * (power[1:] + power[:-1]) * np.diff(ts))])
    assert ham[-1] < 0.9 * ham[0]  # damping is doing something
    np.testing.assert_allclose(ham - ham[0], -work, atol=2e-3 * ham[0])


def test_free_vibration_along_a_mode_runs_at_its_natural_frequency():
    scene = build_scene("focusing-24x16", nx=8, ny=6)
    modes = modal_analysis(scene)
    k = 3
    f_hz = modes.frequencies_hz[k]
    phi = modes.shapes[:, k]
    q0 = 1e-3 * phi / np.max(np.abs(phi[modes.free % 3 != 2]))  # 1e-3 mm peak translation
    sim = jax.jit(make_simulator(scene.lattice, scene.supports, SolverConfig(rtol=1e-11, atol=1e-11)))
    period_ms = 1e3 / f_hz
    ts = jnp.linspace(0.0, 6 * period_ms, 3001)
    ld = Loading(amplitude=0.0)
    sol = check_solution(sim(jnp.asarray(scene.design), scene.material.undamped(), ld, ts,
                             (jnp.asarray(q0), jnp.zeros_like(jnp.asarray(q0)))), SolverConfig())
    qf = np.asarray(sol.q).reshape(ts.size, -1)[:, modes.free]
    modal = qf @ (modes.masses * phi)  # modal coordinate
    s = np.sign(modal)
    idx = np.nonzero(s[1:] != s[:-1])[0]
    t = np.asarray(ts)
    crossings = [t[i] - modal[i] * (t[i + 1] - t[i]) / (modal[i + 1] - modal[i]) for i in idx]
    measured = (len(crossings) - 1) / (2 * (crossings[-1] - crossings[0])) * 1e3
    assert measured == pytest.approx(f_hz, rel=1e-3)


def test_highest_mode_of_the_focusing_lattice():
    modes = modal_analysis(build_scene("focusing-24x16"))
    assert modes.frequencies_hz.size == 1110
    assert 3.5e3 < modes.frequencies_hz[-1] < 6e3  # ~4.6 kHz, sets the explicit step
    assert modes.frequencies_hz[0] > 0.5  # corner clamps remove the rigid-body modes


def test_step_budget_exhaustion_is_reported_not_returned():
    scene = build_scene("focusing-24x16", nx=6, ny=6)
    config = SolverConfig(max_steps=20)
    sim = jax.jit(make_simulator(scene.lattice, scene.supports, config))
    sol = sim(jnp.asarray(scene.design), scene.material, scene.loading, jnp.asarray(scene.sample_times))
    with pytest.raises(SimulationError, match="step budget"):
        check_solution(sol, config)


def test_modes_about_a_precompressed_state_are_stable_and_shifted():
    from design_engine.solve.run import prestressed_state

    scene = build_scene("protection-24x18", nx=8, ny=8, strain=0.03)
    q = prestressed_state(scene)
    top = scene.stage_units_top
    # stage rows sit at -delta/2 = -(N_y - 1) s eps / 2 at the end of the ramp
    np.testing.assert_allclose(q[top, 1], -0.5 * 7 * 15.0 * 0.03, rtol=1e-9)
    ref = modal_analysis(scene).frequencies_hz
    pre = modal_analysis(scene, q).frequencies_hz
    assert np.all(pre > 0)
    assert abs(pre[0] - ref[0]) / ref[0] > 1e-2  # pre-stress changes the spectrum
