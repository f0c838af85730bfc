"""`linalg.make_sparse_spd_solve`: the block Cholesky in a lattice Hessian's banded order (the
static solver's Newton steps) equals a dense solve, differentiates like one, and fails like the
dense Cholesky on a matrix that is not positive definite."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from design_engine.physics.lattice import quads
from design_engine.physics.linalg import make_sparse_spd_solve


def _lattice_matrix(nx: int, ny: int, seed: int = 0):
    """An SPD matrix with a lattice Hessian's pattern (3 DOFs a unit, a unit coupled to itself
    and to its bonded neighbours), its unknowns in a shuffled order: (A, rows, cols)."""
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
    return a, rows, cols


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


def test_a_matrix_that_is_not_positive_definite_gives_non_finite_values():
    a, rows, cols = _lattice_matrix(8, 6)
    a[7, 7] = -1e3
    solve = make_sparse_spd_solve(a.shape[0], rows, cols)
    x = solve(jnp.asarray(a), jnp.ones(a.shape[0]))
    assert not np.all(np.isfinite(np.asarray(x)))
