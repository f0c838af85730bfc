"""Fixed-step velocity Verlet for M q'' = F(q, t) - C q' (one force evaluation per step).

Kick-drift-kick: the first half kick treats damping explicitly, the second implicitly (closed form,
C and M diagonal), which keeps the scheme second order and symplectic when C = 0. Explicit, so
it is stable only for dt < 2 / omega_max (the highest natural frequency, see `modal`); the
contact barrier stiffens without bound, so a scene driven into contact needs a margin or the
adaptive solver. Differentiation is discretise-then-optimise through `lax.scan`.
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp


class FixedStepVerlet(eqx.Module):
    """Velocity Verlet with at most `max_dt` (ms) per step; steps are fitted between samples.

    Attributes:
        max_dt: largest step, ms. Stability needs max_dt < 2 / omega_max (omega in rad/ms).
        remat: recompute the steps between two samples in the backward pass instead of storing
            them (less memory, one more forward pass).
    """

    max_dt: float = eqx.field(static=True, default=0.05)
    remat: bool = eqx.field(static=True, default=False)

    def __check_init__(self):
        if not self.max_dt > 0:
            raise ValueError(f"max_dt must be positive, got {self.max_dt} ms")


def substeps(interval: float, max_dt: float) -> int:
    """Number of equal steps of at most `max_dt` that cover `interval` (at least 1)."""
    return max(1, math.ceil(interval / max_dt - 1e-9))


def march(step, carry, ts, t0: float, n_pre: int, n_sub: int, remat: bool = False):
    """Drive a one-step map through the sample times (shared by every fixed-step scheme).

    Args:
        step: `step(carry, t, dt) -> carry`; `carry[0], carry[1]` are the sampled q and v.
        carry: state at t0.
        ts: [n_t] sample times (the first may equal t0).
        n_pre: steps from t0 to ts[0] (static; 0 when ts[0] == t0).
        n_sub: equal steps between consecutive samples (static).
        remat: recompute the steps between two samples in the backward pass.

    Returns:
        (carry at ts[-1], q [n_t, ...], v [n_t, ...]).
    """

    def advance(carry, t_start, t_end, n):
        dt = (t_end - t_start) / n

        def body(c, k):
            return step(c, t_start + k * dt, dt), None

        return jax.lax.scan(body, carry, jnp.arange(n, dtype=ts.dtype))[0]

    if n_pre > 0:
        carry = advance(carry, jnp.asarray(t0, ts.dtype), ts[0], n_pre)
    first = carry

    def interval(c, pair):
        advance_fn = jax.checkpoint(advance, static_argnums=(3,)) if remat else advance
        c = advance_fn(c, pair[0], pair[1], n_sub)
        return c, (c[0], c[1])

    last, (qs, vs) = jax.lax.scan(interval, carry, jnp.stack([ts[:-1], ts[1:]], axis=1))
    return last, jnp.concatenate([first[0][None], qs]), jnp.concatenate([first[1][None], vs])


def integrate(method: FixedStepVerlet, force, inv_mass, damping, y0, ts, t0: float, n_pre: int,
              n_sub: int):
    """Integrate from t0 through the sample times.

    Args:
        method: the scheme settings.
        force: `force(q, t) -> F` ([n] -> [n]), F = -dV/dq.
        inv_mass, damping: [n] diagonal inverse mass and damping.
        y0: (q0, v0), each [n].
        ts: [n_t] sample times (the first may equal t0).
        n_pre: steps from t0 to ts[0] (static; 0 when ts[0] == t0).
        n_sub: steps between consecutive samples (static).

    Returns:
        (q [n_t, n], v [n_t, n]) at the sample times.
    """
    half_c = 0.5 * inv_mass * damping

    def step(carry, t, dt):
        q, v, f = carry
        v_half = v + 0.5 * dt * inv_mass * (f - damping * v)
        q1 = q + dt * v_half
        f1 = force(q1, t + dt)
        v1 = (v_half + 0.5 * dt * inv_mass * f1) / (1.0 + dt * half_c)
        return (q1, v1, f1)

    q0, v0 = y0
    carry = (q0, v0, force(q0, jnp.asarray(t0, ts.dtype)))
    _, qs, vs = march(step, carry, ts, t0, n_pre, n_sub, method.remat)
    return qs, vs
