"""`linalg.make_sparse_spd_solve`: the block Cholesky in a lattice Hessian's banded order (the
static solver's Newton steps) equals a dense solve, differentiates like one, takes the matrix as
a coloured Hessian's products and a shift of its diagonal, and fails like the dense Cholesky on
a matrix that is not positive definite. `linalg.implicit_point`: an
equilibrium's implicit-function derivative, whose solve only a differentiated program holds."""

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from design_engine.physics.lattice import quads
from design_engine.physics.linalg import implicit_point, make_sparse_spd_solve, spd_solve


def _lattice_matrix(nx: int, ny: int, seed: int = 0, seeds: bool = False):
    """An SPD matrix with a lattice Hessian's pattern (3 DOFs a unit, a unit coupled to itself
    and to its bonded neighbours), its unknowns in a shuffled order: (A, rows, cols), and with
    `seeds` the seed of each column by the statics' distance-2 colouring of the units."""
    bonds = np.asarray(quads(nx, ny).bond_blocks)
    n_blocks = nx * ny
    pairs = np.concatenate([np.stack([np.arange(n_blocks)] * 2, 1), bonds, bonds[:, ::-1]])
    rng = np.random.default_rng(seed)
    order = rng.permutation(3 * n_blocks)
    dof = np.arange(3)
    rows = order[(3 * pairs[:, 0, None, None] + dof[:, None]).repeat(3, 2).ravel()]
    cols = order[(3 * pairs[:, 1, None, None] + dof[None, :]).repeat(3, 1).ravel()]
    a = np.zeros((3 * n_blocks,) * 2)
    a[rows, cols] = rng.normal(size=rows.size)
    a = a + a.T
    a += (np.abs(a).sum(axis=1).max() + 1.0) * np.eye(a.shape[0])  # diagonally dominant
    if not seeds:
        return a, rows, cols
    from design_engine.physics.statics import distance2_colouring

    colour = distance2_colouring(n_blocks, bonds)
    seed_of = np.empty(3 * n_blocks, np.int64)
    seed_of[order] = (3 * colour[:, None] + dof[None, :]).ravel()
    return a, rows, cols, seed_of


@pytest.mark.parametrize("size", [(12, 10), (5, 4)])
def test_the_banded_solve_equals_the_dense_one_and_its_derivative(size):
    a, rows, cols = _lattice_matrix(*size)
    n = a.shape[0]
    solve = make_sparse_spd_solve(n, rows, cols)
    assert solve.blocks >= 3 and solve.block_size < n / 2  # the banded path, not the dense
    b = np.random.default_rng(1).normal(size=n)
    x = np.asarray(jax.jit(solve)(jnp.asarray(a), jnp.asarray(b)))
    np.testing.assert_allclose(x, np.linalg.solve(a, b), rtol=1e-10, atol=1e-13)
    w = np.random.default_rng(2).normal(size=n)
    g = jax.grad(lambda v: jnp.dot(solve(jnp.asarray(a), v), w))(jnp.asarray(b))
    np.testing.assert_allclose(np.asarray(g), np.linalg.solve(a.T, w), rtol=1e-10, atol=1e-13)


@pytest.mark.parametrize("size", [(12, 10), (3, 2)])
def test_a_hessian_given_as_coloured_products_solves_as_the_matrix_with_its_shift(size):
    """The products of A with one seed vector per colour (the static solver's Hessian, which
    it never assembles) solve as A itself, and `shift` adds to the diagonal: on the banded
    path (12x10) and the dense one (3x2, two blocks)."""
    a, rows, cols, seed_of = _lattice_matrix(*size, seeds=True)
    n = a.shape[0]
    seeds = np.zeros((seed_of.max() + 1, n))
    seeds[seed_of, np.arange(n)] = 1.0
    products = seeds @ a  # A symmetric: row s is A times seed vector s
    assert products.shape[0] < n / 2 or size == (3, 2)
    solve = make_sparse_spd_solve(n, rows, cols, seed_of=seed_of)
    assert (solve.blocks >= 3) == (size == (12, 10))
    from_matrix = jax.jit(make_sparse_spd_solve(n, rows, cols))
    b = np.random.default_rng(1).normal(size=n)
    for shift in (0.0, 2.5):
        x = np.asarray(jax.jit(solve)(jnp.asarray(products), jnp.asarray(b), shift))
        np.testing.assert_allclose(x, np.linalg.solve(a + shift * np.eye(n), b), rtol=1e-10,
                                   atol=1e-13)
        # the same entries read, the same arithmetic after
        np.testing.assert_allclose(x, np.asarray(from_matrix(jnp.asarray(a), jnp.asarray(b),
                                                             shift)), rtol=1e-14, atol=1e-16)


def test_a_matrix_that_is_not_positive_definite_gives_non_finite_values():
    a, rows, cols = _lattice_matrix(8, 6)
    a[7, 7] = -1e3
    solve = make_sparse_spd_solve(a.shape[0], rows, cols)
    x = solve(jnp.asarray(a), jnp.ones(a.shape[0]))
    assert not np.all(np.isfinite(np.asarray(x)))


def test_an_implicit_point_is_the_equilibrium_and_differentiates_like_a_re_solved_one():
    """g(q; theta) = sinh(q) + A q - theta = 0 (A SPD): the point's value is the equilibrium
    it is given, to the bit; its Jacobian, forward and reverse, equals central differences of
    equilibria re-solved at theta +- h; the value's program holds no solve (no loop of
    `spd_solve`), the differentiated one does."""
    rng = np.random.default_rng(0)
    m = rng.normal(size=(6, 6))
    a = m @ m.T + 6.0 * np.eye(6)

    def g(q, theta):
        return jnp.sinh(q) + jnp.asarray(a) @ q - theta

    def equilibrium(theta):  # Newton in float64, converged to rounding
        q = np.zeros(6)
        for _ in range(50):
            q = q - np.linalg.solve(np.diag(np.cosh(q)) + a, np.sinh(q) + a @ q - theta)
        return q

    def point(theta, q_s):
        h_s = jnp.diag(jnp.cosh(q_s)) + jnp.asarray(a)
        return implicit_point(q_s, lambda th: -spd_solve(h_s, g(q_s, th)), theta)

    theta = rng.normal(size=6)
    q_s = equilibrium(theta)
    assert np.abs(np.sinh(q_s) + a @ q_s - theta).max() < 1e-12
    np.testing.assert_array_equal(np.asarray(jax.jit(point)(theta, q_s)), q_s)
    h = 1e-5
    fd = np.stack([(equilibrium(theta + h * e) - equilibrium(theta - h * e)) / (2 * h)
                   for e in np.eye(6)], axis=1)
    forward = np.asarray(jax.jacfwd(point)(theta, q_s))
    reverse = np.asarray(jax.jacrev(point)(theta, q_s))
    np.testing.assert_allclose(forward, fd, rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(reverse, forward, rtol=1e-12, atol=1e-15)

    def has_loop(fn):  # spd_solve's elimination: a while or a scan (its bounds are static)
        return re.search(r"\b(while|scan)\[", str(jax.make_jaxpr(fn)(theta, q_s))) is not None

    assert not has_loop(point) and has_loop(jax.jacfwd(point)) and has_loop(jax.jacrev(point))
