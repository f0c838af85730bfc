"""Edge directions and the signed angles between them (void and vertex angles, spec 3.2).

Shared by the manufacturability constraints (reference geometry) and the contact law (which
needs the reference void angles and then rotates them with the blocks).
"""

import jax.numpy as jnp
import numpy as np

from design_engine._types import Array, Float, Vertices
from design_engine.physics.lattice import Lattice


def signed_angle(a, b):
    """Signed angle from vectors a to b, atan2(a x b, a . b) in (-pi, pi]; shapes [..., 2]."""
    cross = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    dot = a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1]
    return jnp.arctan2(cross, dot)


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
