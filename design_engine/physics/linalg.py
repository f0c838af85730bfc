"""Small dense linear algebra in plain jax (no LAPACK custom calls)."""

import jax
import jax.numpy as jnp


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


def implicit_point(q_s, step):
    """An equilibrium q_s with the implicit-function derivative: value q_s exactly, derivative
    that of `step` = -H_s^-1 g(q_s; theta) with q_s and H_s held constant (`stop_gradient`),
    i.e. dq/dtheta = -H^-1 dg/dtheta, exact where g(q_s) = 0."""
    return q_s + (step - jax.lax.stop_gradient(step))
