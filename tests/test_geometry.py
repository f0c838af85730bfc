"""Lattice counts, the design map, mass properties and the manufacturability constraints."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from design_engine.design.constraints import (ConstraintLimits, angle_constraints, edge_constraints,
                                              make_constraints)
from design_engine.physics.angles import bond_angles
from design_engine.physics.geometry import (InvalidDesignError, block_geometry, check_design,
                                            polygon_properties)
from design_engine.physics.lattice import kagome, periodic_design, quads, vertex_offsets


def test_quads_counts_and_initial_design():
    lat = quads(24, 16)
    assert (lat.n_blocks, lat.n_bonds, lat.n_design) == (384, 728, 1616)
    x = periodic_design(lat, math.radians(25))
    g = block_geometry(lat, jnp.asarray(x))
    t0 = math.tan(math.radians(25))
    a = 6.375
    expected = np.array([(a, -a * t0), (a * t0, a), (-a, a * t0), (-a * t0, -a)])
    np.testing.assert_allclose(g.arms[0], expected, atol=1e-12)
    np.testing.assert_allclose(g.centroids[0], [0.0, 0.0], atol=1e-12)
    edges = jnp.linalg.norm(jnp.roll(g.arms, 1, axis=1) - g.arms, axis=-1)
    np.testing.assert_allclose(edges, 9.94763, atol=1e-5)
    ang = bond_angles(lat, g.arms)
    np.testing.assert_allclose(np.mod(ang["beta1"], 2 * np.pi), np.pi / 2, atol=1e-12)
    voids = np.degrees(np.concatenate([ang["alpha1"], ang["alpha2"]]))
    assert set(np.round(voids, 6)) == {40.0, 140.0}
    lim = ConstraintLimits.for_lattice(lat)
    assert angle_constraints(lat, jnp.asarray(x), lim).size + edge_constraints(lat, jnp.asarray(x), lim).size == 4448


def test_kagome_counts_and_mass_properties():
    lat = kagome(20, 12)
    assert (lat.n_blocks, lat.n_bonds, lat.n_design) == (480, 688, 1504)
    g = block_geometry(lat, jnp.zeros(lat.n_design))
    np.testing.assert_allclose(g.areas, 0.070175913 * 20**2, rtol=1e-7)
    np.testing.assert_allclose(g.polar_moments, 9.47751e-4 * 20**4, rtol=1e-5)
    edges = jnp.linalg.norm(jnp.roll(g.arms, 1, axis=1) - g.arms, axis=-1)
    np.testing.assert_allclose(edges, 8.0514, atol=1e-4)
    ang = bond_angles(lat, g.arms)
    np.testing.assert_allclose(np.degrees(np.concatenate([ang["alpha1"], ang["alpha2"]])), 120.0, atol=1e-9)


def test_bond_vectors_are_fixed_for_any_design():
    lat = quads(5, 4)
    x = np.random.default_rng(0).uniform(-2, 2, lat.n_design)
    g = block_geometry(lat, jnp.asarray(x))
    nodes = (g.centroids[:, None, :] + g.arms).reshape(-1, 2)
    ell = nodes[lat.bonds[:, 1]] - nodes[lat.bonds[:, 0]]
    np.testing.assert_allclose(ell, lat.bond_r0, atol=1e-12)


@pytest.mark.parametrize("start", [0, 1, 3])
def test_polygon_properties_rectangle_and_triangle(start):
    w, h = 3.0, 2.0
    rect = np.roll(np.array([[1, 1], [1 + w, 1], [1 + w, 1 + h], [1, 1 + h]], float), start, axis=0)
    area, cent, polar = polygon_properties(jnp.asarray(rect))
    assert area == pytest.approx(w * h)
    np.testing.assert_allclose(cent, [1 + w / 2, 1 + h / 2])
    assert polar == pytest.approx(w * h * (w**2 + h**2) / 12)
    tri = np.array([[0, 0], [3, 0], [0, 3]], float)
    area, cent, polar = polygon_properties(jnp.asarray(tri))
    assert area == pytest.approx(4.5)
    np.testing.assert_allclose(cent, [1, 1])
    # right isosceles triangle, legs b: I_c = b^4/36 * 2 (Ix + Iy about centroid)
    assert polar == pytest.approx(2 * 3**4 / 36)


def test_square_unit_closed_form_mass_properties():
    lat = quads(3, 3)
    g = block_geometry(lat, jnp.zeros(lat.n_design))
    np.testing.assert_allclose(g.areas, 0.36125 * 15**2, rtol=1e-12)
    np.testing.assert_allclose(g.polar_moments, 0.02175026 * 15**4, rtol=1e-7)
    g25 = block_geometry(lat, jnp.asarray(periodic_design(lat, math.radians(25))))
    np.testing.assert_allclose(g25.areas, 98.955, rtol=1e-5)


def test_void_constraint_catches_overlap_that_reference_wrap_misses():
    lat = quads(3, 3)
    x = periodic_design(lat, 0.0).copy()
    # V[0, 1] moves the top vertex of unit 0 (and the bottom vertex of unit 3) 14 mm to the right:
    # unit 0's upper right edge swings past unit 1's upper left edge, a void of about -5 deg
    v01 = (4 * 3) + 0 * 4 + 1
    x[2 * v01] += 14.0
    ours = angle_constraints(lat, jnp.asarray(x), ConstraintLimits.for_lattice(lat))
    ref = angle_constraints(lat, jnp.asarray(x),
                            ConstraintLimits.for_lattice(lat, reference_void_wrap=True))
    n = lat.n_bonds
    assert float(jnp.max(ours[: 2 * n])) > 0.0  # infeasible: negative void detected
    assert float(jnp.max(ref[: 2 * n])) <= 0.0  # the reference's wrap lets it pass


def test_constraint_jacobians_match_finite_differences():
    lat = quads(4, 3)
    rng = np.random.default_rng(1)
    x = periodic_design(lat, math.radians(20)) + rng.uniform(-0.5, 0.5, lat.n_design)
    d = rng.normal(size=lat.n_design)
    d /= np.linalg.norm(d)
    h = 1e-5
    for fn in make_constraints(lat, ConstraintLimits.for_lattice(lat)):
        g, jac = fn(jnp.asarray(x))
        fd = (fn(jnp.asarray(x + h * d))[0] - fn(jnp.asarray(x - h * d))[0]) / (2 * h)
        np.testing.assert_allclose(jac @ d, fd, rtol=1e-6, atol=1e-8)


def test_invalid_designs_are_rejected_with_clear_messages():
    lat = quads(3, 3)
    with pytest.raises(InvalidDesignError, match="needs 48 values"):
        check_design(lat, np.zeros(10))
    with pytest.raises(InvalidDesignError, match="non-finite"):
        check_design(lat, np.full(lat.n_design, np.nan))
    x = periodic_design(lat, 0.3).copy()
    x[2:4] = [20.0, 0.0]  # H[0, 1]: push the left vertex of unit 3 through the unit
    with pytest.raises(InvalidDesignError, match="block 3"):
        check_design(lat, x)
    x = periodic_design(lat, 0.0).copy()
    x[2 * ((4 * 3) + 1)] += 20.0  # V[0, 1]: unit 0 reaches 5 mm into unit 1 (a real overlap)
    with pytest.raises(InvalidDesignError, match="block 0 overlaps block 1"):
        check_design(lat, x)
    for bias in (0.0, 0.3, math.radians(44)):  # the periodic designs themselves are fine
        check_design(lat, periodic_design(lat, bias))
    with pytest.raises(ValueError, match="bias angle"):
        periodic_design(lat, math.radians(50))
    r = vertex_offsets(lat, jnp.asarray(periodic_design(lat, 0.2)))
    assert r.shape == (9, 4, 2)
    jax.block_until_ready(r)
