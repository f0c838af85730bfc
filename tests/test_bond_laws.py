"""Bond kinematics apart from the laws: hand values for one bond, and a pluggable law."""

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from design_engine.physics.energy import (DEFAULT_MODEL, BondMeasures, Model, bond_geometry,
                                          contact_law, ligament_law, make_bond_measures,
                                          make_bond_terms, make_energy, void_stiffness)
from design_engine.physics.geometry import block_geometry
from design_engine.physics.lattice import periodic_design, quads
from design_engine.physics.material import Material


def _one_bond():
    lat = quads(2, 2)  # bond 0 is the horizontal ligament r0 = (l0, 0) from unit 0 to unit 1
    geom = block_geometry(lat, jnp.zeros(lat.n_design))
    return lat, geom, bond_geometry(lat, geom), Material.paper(lat)


def test_measures_and_ligament_law_match_a_hand_computation_for_one_bond():
    lat, geom, bonds, mat = _one_bond()
    l0 = lat.ligament_length
    measures = make_bond_measures(lat)
    # unit 1 translated by (du, dv): the ligament becomes (l0 + du, dv)
    du, dv = 0.1, 0.05
    m = measures(jnp.zeros((4, 3)).at[1, :2].set([du, dv]), bonds)
    strain = math.hypot(l0 + du, dv) / l0 - 1.0
    shear = math.atan2(dv, l0 + du)
    assert float(m.strain[0]) == pytest.approx(strain, rel=1e-12)
    assert float(m.shear[0]) == pytest.approx(shear, rel=1e-12)
    assert float(m.bend[0]) == 0.0
    e = ligament_law(m, mat)
    assert float(e["stretch"][0]) == pytest.approx(0.5 * 120.0 * (strain * l0) ** 2, rel=1e-12)
    assert float(e["shear"][0]) == pytest.approx(0.5 * 1.19 * (shear * l0) ** 2, rel=1e-12)
    assert float(e["bend"][0]) == 0.0
    # unit 1 turned by theta about its bond node: the ligament stays, the mean rotation is
    # theta / 2, so psi = -theta / 2, and the voids turn by -theta, +theta
    theta = 0.3
    d2 = np.asarray(geom.arms[1, int(lat.bond_vertices[0, 1])])
    rot = np.array([[math.cos(theta), -math.sin(theta)], [math.sin(theta), math.cos(theta)]])
    q = jnp.zeros((4, 3)).at[1].set(jnp.asarray([*(d2 - rot @ d2), theta]))
    m = measures(q, bonds)
    assert abs(float(m.strain[0])) < 1e-14
    assert float(m.shear[0]) == pytest.approx(-theta / 2, rel=1e-12)
    assert float(m.bend[0]) == pytest.approx(theta, rel=1e-12)
    ref = np.asarray(bonds.void_ref[0])
    want = np.mod(ref + [-theta, theta] + math.pi, 2 * math.pi) - math.pi
    np.testing.assert_allclose(np.asarray(m.voids[0]), want, rtol=1e-12)
    total = sum(float(v[0]) for v in ligament_law(m, mat).values())
    assert total == pytest.approx(0.5 * 1.19 * (theta / 2 * l0) ** 2 + 0.5 * 1.5 * theta**2,
                                  rel=1e-12)


def test_contact_law_matches_the_spot_value_on_both_voids():
    _, _, _, mat = _one_bond()  # k_c = 1.5 N mm, theta_min -15 deg, theta_cut -10 deg
    one = jnp.zeros(1)
    m = BondMeasures(strain=one, shear=one, bend=one, rest_length=2.25,
                     voids=jnp.radians(jnp.asarray([[-12.5, 10.0]])))
    assert float(contact_law(m, mat)["contact"][0]) == pytest.approx(1.9039e-3, rel=1e-4)
    m = eqx.tree_at(lambda mm: mm.voids, m, jnp.radians(jnp.asarray([[-12.5, -12.5]])))
    assert float(contact_law(m, mat)["contact"][0]) == pytest.approx(2 * 1.9039e-3, rel=1e-4)


def test_a_new_law_is_one_function_that_the_bond_map_calls():
    lat = quads(5, 4)
    x = periodic_design(lat, math.radians(25))
    bonds = bond_geometry(lat, block_geometry(lat, jnp.asarray(x)))
    mat = Material.paper(lat)
    q = jnp.asarray(np.random.default_rng(4).normal(size=(lat.n_blocks, 3)) * 0.8)
    energy = make_energy(lat)
    # the default model, passed explicitly, is the same function
    explicit = make_energy(lat, model=Model(ligament_law, contact_law))
    assert float(explicit(q, bonds, mat)) == float(energy(q, bonds, mat))
    assert float(energy(q, bonds, mat)) == float(jnp.sum(sum(make_bond_terms(lat)(q, bonds,
                                                                                 mat).values())))

    def quartic_bend(m: BondMeasures, mat: Material):
        """A stiffening hinge: k_b dtheta^4 / 4 (mJ) on top of the quadratic bending."""
        return {"bend4": 0.25 * mat.k_bend * m.bend**4}

    model = Model(extra=(quartic_bend,))
    terms = make_bond_terms(lat, model=model)(q, bonds, mat)
    assert list(terms) == ["stretch", "shear", "bend", "contact", "bend4"]
    bend = make_bond_measures(lat)(q, bonds).bend
    def extra(qq):
        return jnp.sum(0.25 * mat.k_bend * make_bond_measures(lat)(qq, bonds).bend ** 4)

    np.testing.assert_allclose(np.asarray(terms["bend4"]), np.asarray(0.25 * 1.5 * bend**4),
                               rtol=1e-14)
    extended = make_energy(lat, model=model)
    assert float(extended(q, bonds, mat)) == pytest.approx(
        float(energy(q, bonds, mat) + extra(q)), rel=1e-13)
    np.testing.assert_allclose(np.asarray(jax.grad(extended)(q, bonds, mat)),
                               np.asarray(jax.grad(energy)(q, bonds, mat) + jax.grad(extra)(q)),
                               rtol=1e-10, atol=1e-12)
    with pytest.raises(ValueError, match="two laws"):
        make_bond_terms(lat, model=Model(extra=(ligament_law,)))(q, bonds, mat)


def hardening_ligament(m: BondMeasures, mat: Material):
    """A new law, written in one place: the ligament of spec 5.1 twice as stiff in stretch, with
    a hinge that hardens cubically (moment k_bend (dtheta + dtheta^3 / 0.1^2)), for the test
    below."""
    terms = ligament_law(m, mat)
    terms["stretch"] = 2.0 * terms["stretch"]
    terms["bend"] = terms["bend"] + 0.25 * mat.k_bend * m.bend**4 / 0.01
    return terms


def stiff_contact(m: BondMeasures, mat: Material):
    """The default barrier, four times as stiff."""
    return {"contact": 4.0 * contact_law(m, mat)["contact"]}


def test_the_contact_frequency_is_the_law_s_own():
    """The solver policy's contact stiffness is differentiated from the law: the default
    barrier's closed form k_c (1 + 3 tau^2) / (1 - tau^2)^3 to rounding, and a law four times
    as stiff has twice the frequency without a line of policy code changed."""
    from design_engine.solve.policy import contact_frequency

    _, _, _, mat = _one_bond()
    span = float(mat.contact_cutoff - mat.contact_min)
    for tau in (0.05, 0.5, 0.9):
        alpha = float(mat.contact_cutoff) - tau * span
        closed = float(mat.k_contact) * (1 + 3 * tau**2) / (1 - tau**2) ** 3
        assert void_stiffness(DEFAULT_MODEL, mat, alpha) == pytest.approx(closed, rel=1e-10)
    margin = 0.3 * span
    w = contact_frequency(margin, mat, 2.0)
    assert contact_frequency(margin, mat, 2.0, Model(contact=stiff_contact)) == pytest.approx(
        2.0 * w, rel=1e-10)
    assert w == pytest.approx(math.sqrt(2 * float(mat.k_contact) * (1 + 3 * 0.49)
                                        / (1 - 0.49) ** 3 / 2.0), rel=1e-10)


def test_a_new_law_reaches_the_simulator_the_gradient_and_the_policy():
    """A scene carrying a model with the new ligament law: the policy measures its stiffer
    lattice (a smaller fixed step), the simulation differs from the default model's, and the
    gradient through it matches a central finite difference."""
    from design_engine.physics.scenes import build_scene
    from design_engine.solve.policy import choose_config
    from design_engine.solve.run import checked, make_objective

    base = build_scene("focusing-24x16", nx=4, ny=3, amplitude_m=2e-3)
    new = dataclasses.replace(base, model=Model(ligament=hardening_ligament))
    c_base, c_new = choose_config(base), choose_config(new)
    # the highest mode is the ligaments' stretch: twice as stiff, sqrt(2) x the frequency
    assert c_new.omega_max == pytest.approx(math.sqrt(2) * c_base.omega_max, rel=0.05)
    assert c_new.config.solver.max_dt < c_base.config.solver.max_dt
    # the new model's step in float64 (the policy's float32 first try is for speed, not for
    # finite differences), both models solved with it
    cfg = dataclasses.replace(c_new.config, dtype="float64")
    x = jnp.asarray(base.design)
    vg = make_objective(new, cfg)[0]
    (j_new, _), grad = checked(vg(x), cfg)
    j_base = checked(make_objective(base, cfg)[1](x), cfg)[0]
    assert abs(float(j_new) / float(j_base) - 1) > 0.01, (j_base, j_new)
    d = np.random.default_rng(2).normal(size=x.size)
    d /= np.linalg.norm(d)
    h = 1e-4
    fd = (float(checked(vg(x + h * d), cfg)[0][0]) - float(checked(vg(x - h * d), cfg)[0][0])) \
        / (2 * h)
    assert float(jnp.dot(grad, d)) == pytest.approx(fd, rel=1e-4)
