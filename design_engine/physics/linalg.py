"""Small linear algebra in jax: a dense SPD solve in plain jax (no LAPACK custom calls), the
implicit-function point, and a sparse SPD solve by block Cholesky in banded order (LAPACK)."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import reverse_cuthill_mckee


def spd_solve(A, b):
    """x = A^-1 b for a symmetric positive definite [n, n] A, by Gaussian elimination without
    pivoting in plain jax (no LAPACK call: XLA's CPU runtime can deadlock when several LAPACK
    custom calls run concurrently inside loops on few cores)."""
    n = A.shape[0]
    idx = jnp.arange(n)

    def eliminate(k, ab):
        a, v = ab
        f = jnp.where(idx > k, a[:, k] / a[k, k], 0.0)
        return a - f[:, None] * a[k][None, :], v - f * v[k]

    a, v = jax.lax.fori_loop(0, n, eliminate, (A, b))

    def back(i, x):
        k = n - 1 - i
        return x.at[k].set((v[k] - a[k] @ x) / a[k, k])

    return jax.lax.fori_loop(0, n, back, jnp.zeros_like(b))


def implicit_point(q_s, step, *theta):
    """An equilibrium q_s with the implicit-function derivative: value q_s exactly, derivative
    that of `step(*theta)` = -H_s^-1 g(q_s; theta) with q_s, H_s and whatever else `step` closes
    over held constant (`stop_gradient`), i.e. dq/dtheta = -H^-1 dg/dtheta, exact where
    g(q_s) = 0. `step` is traced into the program only where the point is differentiated, so a
    forward-only program holds no Hessian solve (a static start's value program compiled 1.3 s
    sooner, 6x6 protection at 7 %)."""
    closed, consts = jax.closure_convert(step, *theta)
    return _held_point(closed, jax.lax.stop_gradient(q_s), jax.lax.stop_gradient(consts), theta)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _held_point(step, q_s, consts, theta):
    return q_s


@_held_point.defjvp
def _held_point_jvp(step, primals, tangents):
    q_s, consts, theta = primals
    return q_s, jax.jvp(lambda *t: step(*t, *consts), theta, tangents[2])[1]


def make_sparse_spd_solve(n: int, rows, cols, min_blocks: int = 3, seed_of=None):
    """Factory: `solve(A, b, shift=0.0) -> (A + shift I)^-1 b` for symmetric positive definite
    [n, n] matrices A whose nonzeros lie at (`rows`, `cols`) (both triangles), b of shape [n].

    A comes dense [n, n], or, with `seed_of` [n] given, as the Hessian-vector products of a
    coloured Hessian [n_seeds, n] (`statics.make_sparse_hessian`): A[i, j] is product
    `seed_of[j]`'s entry i where (i, j) is in the pattern, else 0. Either way only the entries
    the factorisation needs are read, so a Hessian in products never becomes a dense matrix
    (on 24x18 at 8 %, the dense assembly, shift and read took about 3 of the 8.5 ms of a Newton
    step; 1146 unknowns).

    The unknowns are reordered by reverse Cuthill-McKee, which makes a lattice's Hessian banded
    (bandwidth about 3 x the units of one row); in that order A is block tridiagonal with
    blocks of the bandwidth's size, and a block Cholesky (a scan over the block rows) costs
    about n s^2 instead of n^3 / 3. With fewer than `min_blocks` blocks the dense Cholesky is
    used. A that is not positive definite gives non-finite values, as the dense Cholesky does.
    `solve.blocks` is the number of blocks (1: dense), `solve.block_size` their size."""
    rows, cols = np.asarray(rows, np.int64), np.asarray(cols, np.int64)
    pattern = csr_matrix((np.ones(rows.size), (rows, cols)), shape=(n, n))
    perm = np.asarray(reverse_cuthill_mckee(pattern, symmetric_mode=True), np.int64)
    where = np.argsort(perm)  # new position of each unknown
    s = max(1, int(np.max(np.abs(where[rows] - where[cols]), initial=0)))
    nb = -(-n // s)

    def source_index(i, j):
        """Where entry (i, j) (index arrays, -1: padding) lies in A flattened (`zero`, past its
        end: an entry read as 0), and where the real diagonal is."""
        i0, j0 = np.maximum(i, 0), np.maximum(j, 0)
        pad = (i < 0) | (j < 0)
        if seed_of is None:
            flat, zero = i0 * n + j0, n * n
        else:
            seeds = np.asarray(seed_of, np.int64)
            zero = (int(seeds.max()) + 1) * n
            inside = np.asarray(pattern[i0.ravel(), j0.ravel()]).reshape(i.shape) != 0
            flat = np.where(inside, seeds[j0] * n + i0, zero)
        return np.where(pad, zero, flat), (i == j) & ~pad

    def entries(a, index):
        flat = a.reshape(-1)
        return jnp.where(index < flat.size, flat[np.minimum(index, flat.size - 1)], 0.0)

    if nb < min_blocks:
        full, on_diag = source_index(*np.meshgrid(np.arange(n), np.arange(n), indexing="ij"))

        def dense(a, b, shift=0.0):
            m = entries(a, full) + shift * jnp.asarray(on_diag, a.dtype)
            return jax.scipy.linalg.cho_solve(jax.scipy.linalg.cho_factor(m), b)

        dense.blocks, dense.block_size = 1, n
        return dense
    size = nb * s
    tri = jax.scipy.linalg.solve_triangular
    # where the blocks' entries sit in A: the diagonal blocks (k, k) and those below (k, k - 1);
    # past n (the last block's padding) an entry is 0, or 1 on the diagonal
    order = np.concatenate([perm, np.full(size - n, -1)]).reshape(nb, s)
    i_d, j_d = order[:, :, None], order[:, None, :]
    index_d, on_diag = source_index(np.broadcast_to(i_d, (nb, s, s)),
                                    np.broadcast_to(j_d, (nb, s, s)))
    index_s, _ = source_index(np.broadcast_to(order[1:, :, None], (nb - 1, s, s)),
                              np.broadcast_to(order[:-1, None, :], (nb - 1, s, s)))
    pad_d = (i_d < 0) | (j_d < 0)
    eye_pad = np.where(pad_d & (np.arange(s)[:, None] == np.arange(s)[None, :]), 1.0, 0.0)
    pad = size - n

    def solve(a, b, shift=0.0):
        diag = (entries(a, index_d) + jnp.asarray(eye_pad, a.dtype)
                + shift * jnp.asarray(on_diag, a.dtype))  # [nb, s, s]
        sub = entries(a, index_s)  # [nb - 1, s, s]: block (k, k - 1)

        def factor(l_prev, xs):
            d, bk = xs
            c = tri(l_prev, bk.T, lower=True).T  # B_k L_{k-1}^-T
            lk = jnp.linalg.cholesky(d - c @ c.T)
            return lk, (lk, c)

        l0 = jnp.linalg.cholesky(diag[0])
        _, (ls, cs) = jax.lax.scan(factor, l0, (diag[1:], sub))
        ls = jnp.concatenate([l0[None], ls])
        rhs = jnp.pad(b[perm], (0, pad)).reshape(nb, s)

        def forward(y_prev, xs):  # L y = b
            lk, c, bk = xs
            yk = tri(lk, bk - c @ y_prev, lower=True)
            return yk, yk

        y0 = tri(ls[0], rhs[0], lower=True)
        _, ys = jax.lax.scan(forward, y0, (ls[1:], cs, rhs[1:]))
        ys = jnp.concatenate([y0[None], ys])

        def backward(x_next, xs):  # L^T x = y, from the last block row
            lk, c_next, yk = xs
            xk = tri(lk, yk - c_next.T @ x_next, lower=True, trans=1)
            return xk, xk

        x_last = tri(ls[-1], ys[-1], lower=True, trans=1)
        _, xs = jax.lax.scan(backward, x_last, (ls[:-1], cs, ys[:-1]), reverse=True)
        x = jnp.concatenate([xs, x_last[None]]).reshape(size)[:n]
        return x[where]

    solve.blocks, solve.block_size = nb, s
    return solve
