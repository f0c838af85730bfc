"""Objectives and metrics on a `Solution` (spec 8), internal units (mJ, g mm^2/ms).

All are plain functions of the sampled solution, so they differentiate through the solver.
"""

import jax
import jax.numpy as jnp
import numpy as np

from design_engine._types import Array, Float, Scalar
from design_engine.physics.energy import bond_geometry, kinetic_energy, make_bond_terms
from design_engine.physics.geometry import block_geometry
from design_engine.solve.simulate import Solution


def block_kinetic_energy(sol: Solution) -> Float[Array, "n_t n_blocks"]:
    """Kinetic energy of every block at every sample, mJ."""
    return kinetic_energy(sol.qdot, sol.mass, sol.inertia)


def region_energy(sol: Solution, ids) -> Scalar:
    """J_Omega = sum over samples and units of Omega of the kinetic energy, mJ (spec 8)."""
    return jnp.sum(block_kinetic_energy(sol)[:, np.asarray(ids)])


def region_energy_ratio(sol: Solution, ids) -> Scalar:
    """J_Omega / J_(rest of the domain), both summed over the same samples (Fig. 2C metric)."""
    ke = block_kinetic_energy(sol)
    inside = jnp.sum(ke[:, np.asarray(ids)])
    return inside / (jnp.sum(ke) - inside)


def angular_momentum(sol: Solution, ids, point) -> Scalar:
    """J_L = sum_k sum_b [(c_b + u_b - S) x m_b u_b' + J_b theta_b'] (spec 8.6), g mm^2/ms.

    Positive means counter-clockwise. `point` S is [2] mm.
    """
    ids = np.asarray(ids)
    r = sol.centroids[ids][None] + sol.q[:, ids, :2] - jnp.asarray(point)
    v = sol.qdot[:, ids, :2]
    m = sol.mass[ids]
    lin = m * (r[..., 0] * v[..., 1] - r[..., 1] * v[..., 0])
    return jnp.sum(lin + sol.inertia[ids] * sol.qdot[:, ids, 2])


QUANTITIES = ("kinetic_energy", "angular_momentum")


def objective_term(quantity: str, sol: Solution, ids, point=None) -> Scalar:
    """One objective quantity of a target region (the one definition every caller uses).

    "kinetic_energy": J_Omega, mJ summed over the samples (spec 8); "angular_momentum": J_L
    about `point` [2] mm, g mm^2/ms (spec 8.6).
    """
    if quantity == "angular_momentum":
        return angular_momentum(sol, ids, point)
    if quantity == "kinetic_energy":
        return region_energy(sol, ids)
    raise ValueError(f"unknown objective quantity {quantity!r} (one of {', '.join(QUANTITIES)})")


def peak_energy_along_units(sol: Solution, ids) -> Float[Array, " n"]:
    """max over samples of each listed unit's kinetic energy, mJ (Figs. 2F, 4D)."""
    return jnp.max(block_kinetic_energy(sol)[:, np.asarray(ids)], axis=0)


def energy_components(scene, sol: Solution, linearized: bool = False,
                      use_contact: bool = True) -> dict[str, np.ndarray]:
    """Kinetic and potential energy components summed over the lattice at every sample, mJ.

    Returns dict with [n_t] arrays: kinetic, stretch, shear, bend, contact.
    """
    terms_fn = make_bond_terms(scene.lattice, linearized=linearized, use_contact=use_contact,
                               model=scene.model)
    bonds = bond_geometry(scene.lattice, block_geometry(scene.lattice, jnp.asarray(scene.design)))
    per_t = jax.jit(jax.vmap(lambda q: {k: jnp.sum(v) for k, v in
                                        terms_fn(q, bonds, scene.material).items()}))(sol.q)
    out = {"kinetic": np.asarray(jnp.sum(block_kinetic_energy(sol), axis=1))}
    out.update({k: np.asarray(v) for k, v in per_t.items()})
    return out
