"""Edge directions and the signed angles between them (void and vertex angles, spec 3.2).

Shared by the manufacturability constraints (reference geometry) and the contact law (which
needs the reference void angles and then rotates them with the blocks).
"""

import jax
import jax.numpy as jnp
import numpy as np

from design_engine._types import Array, Float, Vertices
from design_engine.physics.lattice import Lattice


# atan2 by octant reduction: atan(t) = atan(c) + atan((t - c) / (1 + t c)) about the nearest
# of c = tan(0), tan(pi/8), tan(pi/4) leaves |u| <= tan(pi/16) = 0.199, where the Taylor series
# u - u^3/3 + u^5/5 - ... to u^25 is exact in float64 (the next term is below 1e-19 of u)
_T1, _T3, _C1 = (float(np.tan(a)) for a in (np.pi / 16, 3 * np.pi / 16, np.pi / 8))  # weak types
_ATAN_SERIES = tuple((-1) ** k / (2 * k + 1) for k in range(1, 13))


@jax.custom_jvp
def atan2(y, x):
    """atan2(y, x) in (-pi, pi], elementwise, within 2 ulp of `jnp.arctan2` (atan2(+-0, x < 0)
    is pi). Arithmetic only: XLA's CPU arctan2 is not vectorised, and in a force evaluation
    its 728 shear angles cost about a sixth of the whole (25 us against 7 us here, 24x16
    units). The derivative is the exact one, (x dy - y dx) / (x^2 + y^2)."""
    ax, ay = jnp.abs(x), jnp.abs(y)
    big, small = jnp.maximum(ax, ay), jnp.minimum(ax, ay)
    t = small / jnp.where(big > 0, big, 1.0)  # in [0, 1]
    past1, past3 = t > _T1, t > _T3
    c = jnp.where(past3, 1.0, jnp.where(past1, _C1, 0.0))
    base = jnp.where(past3, np.pi / 4, jnp.where(past1, np.pi / 8, 0.0))
    u = (t - c) / (1.0 + t * c)
    z = u * u
    series = jnp.full_like(z, _ATAN_SERIES[-1])
    for coefficient in _ATAN_SERIES[-2::-1]:
        series = series * z + coefficient
    a = base + (u + u * z * series)
    a = jnp.where(ay > ax, np.pi / 2 - a, a)
    a = jnp.where(x < 0, np.pi - a, a)
    return jnp.where(y < 0, -a, a)


@atan2.defjvp
def _atan2_jvp(primals, tangents):
    y, x = primals
    dy, dx = tangents
    return atan2(y, x), (x * dy - y * dx) / (x * x + y * y)


def signed_angle(a, b):
    """Signed angle from vectors a to b, atan2(a x b, a . b) in (-pi, pi]; shapes [..., 2]."""
    cross = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    dot = a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1]
    return atan2(cross, dot)


def edge_vectors(arms: Vertices):
    """(e_plus, e_minus) at every vertex: arms[k+1] - arms[k] and arms[k-1] - arms[k], [nb, nv, 2]."""
    e_plus = jnp.roll(arms, -1, axis=1) - arms
    e_minus = jnp.roll(arms, 1, axis=1) - arms
    return e_plus, e_minus


def bond_angles(lattice: Lattice, arms: Vertices) -> dict[str, Float[Array, " n_bonds"]]:
    """Raw signed void angles alpha1, alpha2 and vertex angles beta1, beta2 of every bond (rad).

    alpha1 = angle(e-_{n2} -> e+_{n1}), alpha2 = angle(e-_{n1} -> e+_{n2}),
    beta_i = angle(e+_{n_i} -> e-_{n_i}); all in (-pi, pi], before any wrapping.
    """
    e_plus, e_minus = edge_vectors(arms)
    bb = np.asarray(lattice.bond_blocks)
    bk = np.asarray(lattice.bond_vertices)
    ep1, em1 = e_plus[bb[:, 0], bk[:, 0]], e_minus[bb[:, 0], bk[:, 0]]
    ep2, em2 = e_plus[bb[:, 1], bk[:, 1]], e_minus[bb[:, 1], bk[:, 1]]
    return {
        "alpha1": signed_angle(em2, ep1),
        "alpha2": signed_angle(em1, ep2),
        "beta1": signed_angle(ep1, em1),
        "beta2": signed_angle(ep2, em2),
    }
