"""Energy laws: zero force at reference, rigid-motion invariance, contact barrier, shear wrap."""

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from design_engine.physics.energy import bond_geometry, contact_energy, make_bond_terms, make_energy
from design_engine.physics.geometry import block_geometry
from design_engine.physics.lattice import kagome, periodic_design, quads
from design_engine.physics.material import Material

TH_MIN, TH_CUT, KC = math.radians(-15), math.radians(-10), 1.5


@functools.lru_cache
def _lattice(kind, nx, ny, linearized=False):
    """A lattice and its jitted geometry, energy and bond terms, shared by the tests that use
    the same one (eagerly they were hundreds of single-operation programs: the file took
    25 -> 12 CPU s cold)."""
    lat = (quads if kind == "quads" else kagome)(nx, ny)

    def geometry(x):
        g = block_geometry(lat, x)
        return g, bond_geometry(lat, g)

    return lat, (jax.jit(geometry), jax.jit(make_energy(lat, linearized=linearized)),
                 jax.jit(make_bond_terms(lat, linearized=linearized)))


def _setup(lat, x, **kw):
    """Geometry, bonds, material and the jitted energy of design x on `lat`, a _lattice()."""
    lattice, (geometry, _, _) = _lattice(*lat)
    g, bonds = geometry(jnp.asarray(x))
    return g, bonds, Material.paper(lattice), _lattice(*lat, **kw)[1][1]


@pytest.mark.parametrize("kind", ["quads", "kagome"])
def test_zero_force_at_reference_for_feasible_designs(kind):
    spec = ("quads", 6, 5) if kind == "quads" else ("kagome", 4, 3)
    lat = _lattice(*spec)[0]
    rng = np.random.default_rng(3)
    x = (periodic_design(lat, 0.35) if kind == "quads" else np.zeros(lat.n_design))
    x = x + rng.uniform(-0.3, 0.3, lat.n_design)
    _, bonds, mat, energy = _setup(spec, x)
    force = jax.jit(jax.grad(energy))(jnp.zeros((lat.n_blocks, 3)), bonds, mat)
    # jitted (as the simulator runs it), XLA fuses the reference and the current measures
    # differently: measured 1.5e-13 (quads) and 1.5e-14 (kagome), 4.6e-29 energy; eagerly both
    # were exactly 0. 1e-11 leaves 70x for another CPU's rounding, while the measures off their
    # reference by a random 1e-14 mm/rad already give 6e-11 (measured: stiffness ~6e3), and a
    # wrong reference term O(1)
    assert float(jnp.max(jnp.abs(force))) < 1e-11
    assert float(energy(jnp.zeros((lat.n_blocks, 3)), bonds, mat)) < 1e-20


@pytest.mark.parametrize("angle", [0.7, -2.5, 3 * math.pi])
@pytest.mark.parametrize("linearized", [False])
def test_rigid_motion_stores_no_energy(angle, linearized):
    lat, (_, _, terms) = _lattice("quads", 6, 5, linearized)
    x = periodic_design(lat, math.radians(25))
    g, bonds, mat, energy = _setup(("quads", 6, 5), x, linearized=linearized)
    c = np.asarray(g.centroids)
    rot = np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
    uv = c @ rot.T - c + np.array([3.0, -7.0])
    q = jnp.asarray(np.column_stack([uv, np.full(lat.n_blocks, angle)]))
    assert float(energy(q, bonds, mat)) < 1e-20
    assert float(jnp.max(jnp.abs(terms(q, bonds, mat)["shear"]))) < 1e-20


def test_single_unit_full_turn_is_not_free():
    lat = _lattice("quads", 2, 2)[0]
    _, bonds, mat, energy = _setup(("quads", 2, 2), periodic_design(lat, 0.3))
    q = np.zeros((4, 3))
    q[0, 2] = 2 * math.pi
    # bending is not wrapped: a full turn of one unit stores k_b (2 pi)^2 / 2 per attached bond,
    # and the mean rotation pi carries the reference ligament half a turn: shear angle pi
    per_bond = 0.5 * 1.5 * (2 * math.pi) ** 2 + 0.5 * 1.19 * (math.pi * 2.25) ** 2
    assert float(energy(q, bonds, mat)) == pytest.approx(2 * per_bond, rel=1e-9)


def test_contact_law_values_continuity_and_asymptote():
    f = lambda a: float(contact_energy(jnp.asarray(a), KC, TH_MIN, TH_CUT))  # noqa: E731
    assert f(math.radians(-12.5)) == pytest.approx(1.9039e-3, rel=1e-4)
    for a in (TH_CUT, 0.0, 1.0, TH_MIN - 1e-9, -math.pi):
        assert f(a) == 0.0
    assert f(TH_CUT - 1e-6) < 1e-11  # C1 at the cutoff: energy ~ (delta alpha)^2
    vals = [f(TH_MIN + d) for d in (1e-2, 1e-4, 1e-6)]
    assert vals[0] < vals[1] < vals[2] and vals[2] > 1e2 * vals[0]
    # the two written forms of the middle branch agree
    a = math.radians(-13.7)
    tau = (a - TH_CUT) / (TH_CUT - TH_MIN)
    alt = KC / 4 * (TH_CUT - TH_MIN) ** 2 * (1 / (tau + 1) - 1 / (tau - 1) - 2)
    assert f(a) == pytest.approx(alt, rel=1e-12)


def test_contact_gradient_has_no_nan_anywhere():
    grad = jax.jit(jax.vmap(jax.grad(lambda a: contact_energy(a, KC, TH_MIN, TH_CUT))))
    pts = jnp.concatenate([jnp.linspace(-math.pi, math.pi, 2001),
                           jnp.asarray([TH_MIN, TH_CUT, 2 * TH_CUT - TH_MIN])])
    g = grad(pts)
    assert not bool(jnp.any(jnp.isnan(g)))
    # finite everywhere except exactly at the asymptote theta_min, where the barrier is infinite
    assert bool(jnp.all(jnp.isfinite(g[pts != TH_MIN])))
    # force is continuous at the cutoff (zero on both sides)
    assert abs(float(grad(jnp.asarray([TH_CUT - 1e-9]))[0])) < 1e-6


def test_shear_angle_is_continuous_through_zero_and_bounded():
    lat, (_, _, terms) = _lattice("quads", 2, 2)
    _, bonds, mat, _ = _setup(("quads", 2, 2), np.zeros(lat.n_design))
    # rotate unit 1 rigidly about unit 0's bond node: the ligament turns with it
    psis = []
    for phi in np.linspace(-3 * math.pi, 3 * math.pi, 301):
        q = np.zeros((4, 3))
        q[1, 2] = phi
        psis.append(float(terms(q, bonds, mat)["shear"][0]))
    psis = np.array(psis)
    assert np.all(np.isfinite(psis))
    assert psis.max() <= 0.5 * 1.19 * (math.pi * 2.25) ** 2 + 1e-12


def test_linearised_strains_agree_at_small_motion():
    lat = _lattice("quads", 6, 5)[0]  # the lattice of the tests above: their programs
    x = periodic_design(lat, math.radians(25))
    _, bonds, mat, e_nl = _setup(("quads", 6, 5), x)
    e_lin = _lattice("quads", 6, 5, True)[1][1]
    q = jnp.asarray(np.random.default_rng(2).normal(size=(lat.n_blocks, 3)))
    rel = []
    for h in (1e-2, 1e-3, 1e-4):
        a, b = float(e_nl(h * q, bonds, mat)), float(e_lin(h * q, bonds, mat))
        rel.append(abs(a - b) / a)
    assert rel[2] < 1e-3 and rel[1] < rel[0] / 5 and rel[2] < rel[1] / 5


def test_contact_energy_reads_rotations_in_the_callers_order():
    """`make_contact_energy(order=)` takes unit k's rotation from entry order[k] (the fixed
    step's fast force holds them as [free rotations, prescribed rotations]): the energy and its
    gradient, entry by entry, are those of the rotations in unit order, and of the full model's
    contact term (voids pressed into the barrier, so the law is active)."""
    from design_engine.physics.energy import Model, contact_law, make_contact_energy

    lat = _lattice("quads", 4, 3)[0]
    _, bonds, mat, _ = _setup(("quads", 4, 3), periodic_design(lat, 0.35))
    rng = np.random.default_rng(5)
    # neighbours counter-rotating by about 0.55 rad each close the 50 deg voids on one side of
    # every bond to about -12.5 deg, inside the barrier (-15 to -10 deg)
    sign = np.zeros(lat.n_blocks)
    sign[0] = 1.0
    for _ in range(lat.n_blocks):  # two colours, neighbours apart
        for a, b in np.asarray(lat.bond_blocks):
            sign[b] = sign[b] or -sign[a]
            sign[a] = sign[a] or -sign[b]
    theta = jnp.asarray(-0.545 * sign + rng.uniform(-0.01, 0.01, lat.n_blocks))
    order = rng.permutation(lat.n_blocks)
    held = jnp.zeros(lat.n_blocks).at[order].set(theta)  # unit k's rotation at order[k]
    e_unit, g_unit = jax.value_and_grad(make_contact_energy(lat))(theta, bonds, mat)
    e_held, g_held = jax.value_and_grad(make_contact_energy(lat, order=order))(held, bonds, mat)
    assert float(e_unit) > 0.0  # some void is in the barrier
    assert float(e_held) == pytest.approx(float(e_unit), rel=1e-14)
    np.testing.assert_allclose(np.asarray(g_held)[order], np.asarray(g_unit), rtol=1e-13,
                               atol=1e-13 * float(jnp.max(jnp.abs(g_unit))))
    # the same term as the whole model's, whose rotations are the state's third column
    q = jnp.zeros((lat.n_blocks, 3)).at[:, 2].set(theta)
    only_contact = make_energy(lat, model=Model(ligament=lambda m, _: {}, contact=contact_law))
    assert float(only_contact(q, bonds, mat)) == pytest.approx(float(e_unit), rel=1e-12)
