"""Implicit Newmark (average acceleration) for M q'' = F(q, t) - C q', chord iterations on a
frozen, factored iteration matrix.

Per step (h the step, a the acceleration):
    q1 = q + h v + h^2/4 (a + a1),   v1 = v + h/2 (a + a1),   M a1 + C v1 = F(q1, t + h).
The trapezoidal rule: second order, unconditionally stable for linear stiffness, no numerical
damping, so the stiff ligament-stretch mode does not bound the step; accuracy does. The nonlinear
equation for a1 is solved by a fixed number of chord iterations
    a1 <- a1 - S0^-1 (M a1 + C v1 - F(q1)),   S0 = M + h/2 C + h^2/4 K0,
with K0 the stiffness at the initial state. K0 couples only units joined by a ligament, so with
the row-major unit numbering it is banded: it is assembled from 2b + 1 Hessian-vector products
(b the bandwidth) and S0 is factored once per solve as a block-tridiagonal Cholesky (blocks of b
DOFs), making each iteration one force evaluation plus two short block sweeps. The factor is a
preconditioner only (gradients do not flow through it); a step whose last correction moved q by
more than `tol` did not converge and the solve is reported as failed. Differentiation is
discretise-then-optimise through the iterations.
"""

import math
from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from design_engine.solve.fixed_step import (AbstractFixedStep, Integrator, StepGrid, energy_error,
                                            ledger_start, ledger_step, march)


class ImplicitNewmark(AbstractFixedStep):
    """Trapezoidal Newmark with at most `max_dt` (ms) per step, `iterations` chord iterations.

    Attributes:
        max_dt: largest step, ms (not limited by stability; steps are fitted between samples).
        iterations: chord iterations per step (force evaluations per step).
        tol: largest accepted last correction of q (mm for u, v; rad for theta); above it the
            iterations did not converge and the solve is reported as failed.
        remat: recompute each step from its start state in the backward pass (`march`).
    """

    max_dt: float = eqx.field(static=True, default=0.16)
    iterations: int = eqx.field(static=True, default=3)
    tol: float = eqx.field(static=True, default=1e-4)
    remat: bool = eqx.field(static=True, default=False)
    stability_limited = False

    def __check_init__(self):
        if not self.max_dt > 0:
            raise ValueError(f"max_dt must be positive, got {self.max_dt} ms")
        if self.iterations < 1:
            raise ValueError(f"iterations must be at least 1, got {self.iterations}")

    def make_integrator(self, grid: StepGrid, bond_blocks: np.ndarray, free: np.ndarray,
                        n_dof: int) -> Integrator:
        layout = band_layout(free_dof_pairs(bond_blocks, free, n_dof), free.size)

        def run(force, inv_mass, damping, y0, ts):
            qs, vs, moved, led = integrate(self, force, inv_mass, damping, layout, y0, ts, 0.0,
                                           grid.n_pre, grid.n_sub, grid.dt_nominal)
            return qs, vs, moved <= self.tol, energy_error(led)

        return run

    def force_evaluations(self, num_steps: int) -> int:
        return num_steps * self.iterations + 1  # Hessian-vector products of the factor not counted

    def summary(self) -> dict:
        return {"max_dt_s": self.max_dt * 1e-3, "iterations_per_step": self.iterations}

    def unstable_hint(self) -> str:
        return ""

    def unconverged_message(self) -> str:
        return (f"the implicit iterations did not converge ({self.iterations} chord "
                f"iterations per step left a correction above {self.tol:g} mm/rad): the "
                "stiffness moved too far from the initial one for this step; use a smaller step "
                "or more iterations")


@dataclass(frozen=True)
class BandLayout:
    """Static block-tridiagonal layout of a banded [n, n] matrix (numpy index arrays).

    Attributes:
        n: matrix size; bandwidth: largest |i - j| of a non-zero; block: block size (>= bandwidth,
            so only neighbouring blocks couple); n_blocks: blocks after padding to n_blocks * block.
        diag_index, sub_index: [n_blocks, block, block] flat indices into the compressed
            [n, 2 bandwidth + 1] matrix of Hessian-vector products (-1 where zero or padding).
    """

    n: int
    bandwidth: int
    block: int
    n_blocks: int
    diag_index: np.ndarray
    sub_index: np.ndarray

    @property
    def probes(self) -> int:
        """Hessian-vector products needed to assemble the band: 2 bandwidth + 1."""
        return 2 * self.bandwidth + 1


def band_layout(pairs: np.ndarray, n: int) -> BandLayout:
    """Layout for an [n, n] matrix whose non-zeros couple DOF `pairs` ([m, 2] indices) and the
    diagonal."""
    pairs = np.asarray(pairs).reshape(-1, 2)
    b = int(np.max(np.abs(pairs[:, 0] - pairs[:, 1]))) if pairs.size else 0
    block = max(b, 1)
    nb = math.ceil(n / block)
    w = 2 * b + 1

    def index(row_offset: int) -> np.ndarray:
        k = np.arange(nb)[:, None, None]
        r = np.arange(block)[None, :, None]
        c = np.arange(block)[None, None, :]
        i = (k + row_offset) * block + r
        j = k * block + c
        ok = (np.abs(i - j) <= b) & (i < n) & (j < n)
        return np.where(ok, i * w + np.mod(j, w), -1)

    return BandLayout(n, b, block, nb, index(0), index(1)[:-1] if nb > 1 else index(1)[:0])


def free_dof_pairs(bond_blocks: np.ndarray, free: np.ndarray, n_dof: int) -> np.ndarray:
    """[m, 2] free-DOF index pairs coupled by the energy: the DOFs of the two units of a bond,
    and the DOFs of one unit among themselves."""
    pos = np.full(n_dof, -1)
    pos[free] = np.arange(free.size)
    out = []
    for a, b in np.asarray(bond_blocks):
        dofs = pos[np.r_[3 * a:3 * a + 3, 3 * b:3 * b + 3]]
        dofs = dofs[dofs >= 0]
        out.append(np.stack(np.meshgrid(dofs, dofs), -1).reshape(-1, 2))
    return np.concatenate(out) if out else np.zeros((0, 2), int)


def banded_stiffness(hvp, layout: BandLayout, dtype):
    """[n, 2b + 1] compressed stiffness: column k holds K @ (sum of e_j, j = k mod (2b + 1)), so
    K[i, j] = out[i, j mod (2b + 1)] for |i - j| <= b. `hvp(v) -> K v` ([n] -> [n])."""
    w = layout.probes
    probes = (jnp.arange(layout.n)[None, :] % w == jnp.arange(w)[:, None]).astype(dtype)
    return jax.vmap(hvp)(probes).T


def factor(layout: BandLayout, compressed, diagonal):
    """Block-tridiagonal Cholesky of S = K + diag(`diagonal`) (S symmetric positive definite).

    Args:
        compressed: [n, 2b + 1] from `banded_stiffness`.
        diagonal: [n] added to the diagonal.

    Returns:
        (inv_l [n_blocks, B, B] inverses of the diagonal Cholesky factors,
         w [n_blocks, B, B] off-diagonal factors, w[0] = 0).
    """
    flat = jnp.concatenate([compressed.reshape(-1), jnp.zeros(1, compressed.dtype)])
    d = flat[layout.diag_index]  # index -1 picks the trailing zero
    e = flat[layout.sub_index]
    n_pad = layout.n_blocks * layout.block
    diag = jnp.concatenate([diagonal, jnp.ones(n_pad - layout.n, diagonal.dtype)])
    d = d + jax.vmap(jnp.diag)(diag.reshape(layout.n_blocks, layout.block))
    eye = jnp.eye(layout.block, dtype=compressed.dtype)

    def body(inv_prev, de):
        d_k, e_prev = de
        w_k = e_prev @ inv_prev.T  # E_{k-1} L_{k-1}^-T
        l_k = jnp.linalg.cholesky(d_k - w_k @ w_k.T)
        inv_k = jax.scipy.linalg.solve_triangular(l_k, eye, lower=True)
        return inv_k, (inv_k, w_k)

    e_all = jnp.concatenate([jnp.zeros((1,) + eye.shape, eye.dtype), e])
    _, (inv_l, w) = jax.lax.scan(body, jnp.zeros_like(eye), (d, e_all))
    return inv_l, w


def solve(layout: BandLayout, factors, r):
    """x with S x = r ([n]) from the factors of `factor`."""
    inv_l, w = factors
    n_pad = layout.n_blocks * layout.block
    rb = jnp.concatenate([r, jnp.zeros(n_pad - layout.n, r.dtype)]).reshape(layout.n_blocks, -1)

    def fwd(y_prev, args):
        inv_k, w_k, r_k = args
        y = inv_k @ (r_k - w_k @ y_prev)
        return y, y

    _, y = jax.lax.scan(fwd, jnp.zeros_like(rb[0]), (inv_l, w, rb))
    w_next = jnp.concatenate([w[1:], jnp.zeros_like(w[:1])])

    def bwd(x_next, args):
        inv_k, w_n, y_k = args
        x = inv_k.T @ (y_k - w_n.T @ x_next)
        return x, x

    _, x = jax.lax.scan(bwd, jnp.zeros_like(rb[0]), (inv_l, w_next, y), reverse=True)
    return x.reshape(-1)[:layout.n]


def integrate(method: ImplicitNewmark, force, inv_mass, damping, layout: BandLayout, y0, ts,
              t0: float, n_pre: int, n_sub: int, dt_nominal: float):
    """Integrate from t0 through the sample times.

    Args:
        method: the scheme settings.
        force: `force(q, t) -> (F, (V, P))` (see `fixed_step.Integrator`).
        inv_mass, damping: [n] diagonal inverse mass and damping.
        layout: band layout of the stiffness over the n DOFs.
        y0: (q0, v0), each [n].
        ts: [n_t] sample times; n_pre, n_sub: steps before ts[0] and between samples (static).
        dt_nominal: step the iteration matrix is built for, ms (the largest step).

    Returns:
        (q [n_t, n], v [n_t, n], largest last correction of q over all steps, the final
        `fixed_step.Ledger`; its energy and power are those of the last chord iteration's force
        evaluation, within the accepted correction of the step's end).
    """
    q0, v0 = y0
    t_start = jnp.asarray(t0, ts.dtype)
    mass = 1.0 / inv_mass
    h = jnp.asarray(dt_nominal, ts.dtype)

    def hvp(v):
        return -jax.jvp(lambda q: force(q, t_start)[0], (q0,), (v,))[1]

    k_band = jax.lax.stop_gradient(banded_stiffness(hvp, layout, ts.dtype))
    s_factors = factor(layout, 0.25 * h * h * k_band,
                       jax.lax.stop_gradient(mass + 0.5 * h * damping))

    def step(carry, t, dt):
        q, v, a, worst, led = carry
        q_base = q + dt * v + 0.25 * dt * dt * a
        v_base = v + 0.5 * dt * a

        def chord(a1, _):
            q1 = q_base + 0.25 * dt * dt * a1
            v1 = v_base + 0.5 * dt * a1
            f1, aux1 = force(q1, t + dt)
            residual = mass * a1 + damping * v1 - f1
            delta = solve(layout, s_factors, residual)
            return a1 - delta, (jnp.max(jnp.abs(delta)), aux1)

        a1, (corrections, aux) = jax.lax.scan(chord, a, None, length=method.iterations)
        moved = 0.25 * dt * dt * corrections[-1]
        worst = jnp.maximum(worst, jax.lax.stop_gradient(moved))
        v1 = v_base + 0.5 * dt * a1
        led = ledger_step(led, dt, v, v1, mass, damping,
                          jax.tree_util.tree_map(lambda x: x[-1], aux))
        return (q_base + 0.25 * dt * dt * a1, v1, a1, worst, led)

    f0, aux0 = force(q0, t_start)
    a0 = inv_mass * (f0 - damping * v0)
    carry = (q0, v0, a0, jnp.zeros((), ts.dtype), ledger_start(v0, mass, aux0))
    last, qs, vs = march(step, carry, ts, t0, n_pre, n_sub, method.remat)
    return qs, vs, last[3], last[4]
