"""Potential energy of the network: scalar per-bond laws and their lift over the lattice.

Laws (spec 5): ligament = 1/2 k_l (eps l0)^2 + 1/2 k_s (psi l0)^2 + 1/2 k_b dtheta^2, and the
contact barrier per void angle. Energies in mJ, angles rad, lengths mm. Forces are never written
by hand: the dynamics take `jax.grad` of `make_energy(...)`.
"""

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from design_engine._types import Array, BlockState, Float, Scalar
from design_engine.angles import bond_angles
from design_engine.geometry import BlockGeometry
from design_engine.lattice import Lattice
from design_engine.material import Material

PI = jnp.pi


def wrap(phi):
    """Map angles onto [-pi, pi)."""
    return jnp.mod(phi + PI, 2.0 * PI) - PI


def ligament_energy(strain, shear, bend, l0, k_stretch, k_shear, k_bend):
    """Energy of one ligament (mJ) from axial strain, shear angle (rad), relative rotation (rad)."""
    return 0.5 * k_stretch * (strain * l0) ** 2 + 0.5 * k_shear * (shear * l0) ** 2 + 0.5 * k_bend * bend**2


def contact_energy(alpha, k_contact, theta_min, theta_cut):
    """Contact barrier of one void angle alpha (rad), spec 5.3; mJ.

    Zero for alpha >= theta_cut and for alpha < theta_min (a wide void wrapped to about -pi is
    not contact); in between k/2 (alpha - theta_cut)^2 / (1 - tau^2), which is C1 at theta_cut
    and unbounded as alpha -> theta_min+. The middle branch is evaluated on a clamped tau
    ("double where") so the unused branch never yields NaN gradients.
    """
    span = theta_cut - theta_min
    tau = (alpha - theta_cut) / span
    active = (alpha >= theta_min) & (alpha < theta_cut)
    tau_safe = jnp.where(active, tau, -0.5)
    value = 0.5 * k_contact * span**2 * tau_safe**2 / (1.0 - tau_safe**2)
    return jnp.where(active, value, 0.0)


class BondGeometry(eqx.Module):
    """Design-dependent quantities of every bond, precomputed once per design.

    Attributes:
        arm1, arm2: [n_bonds, 2] centroid-to-node vectors at the two ends, mm.
        void_ref: [n_bonds, 2] reference void angles (alpha1, alpha2), rad.
    """

    arm1: Float[Array, "n_bonds 2"]
    arm2: Float[Array, "n_bonds 2"]
    void_ref: Float[Array, "n_bonds 2"]


def bond_geometry(lattice: Lattice, geom: BlockGeometry) -> BondGeometry:
    """Gather per-bond arms and reference void angles from the block geometry."""
    bb, bk = lattice.bond_blocks, lattice.bond_vertices
    ang = bond_angles(lattice, geom.arms)
    return BondGeometry(
        arm1=geom.arms[bb[:, 0], bk[:, 0]],
        arm2=geom.arms[bb[:, 1], bk[:, 1]],
        void_ref=jnp.stack([ang["alpha1"], ang["alpha2"]], axis=-1),
    )


def _rotate_minus_identity(theta, d):
    """(R(theta) - I) d for [n] angles and [n, 2] vectors."""
    c, s = jnp.cos(theta), jnp.sin(theta)
    return jnp.stack([(c - 1.0) * d[:, 0] - s * d[:, 1], s * d[:, 0] + (c - 1.0) * d[:, 1]], axis=-1)


def make_bond_terms(lattice: Lattice, *, linearized: bool = False, use_contact: bool = True):
    """Factory: `terms(q, bonds, material) -> dict` of per-bond energies (mJ), each [n_bonds].

    Keys: stretch, shear, bend, contact. `q` is [n_blocks, 3] (u mm, v mm, theta rad).
    """
    b1 = np.asarray(lattice.bond_blocks[:, 0])
    b2 = np.asarray(lattice.bond_blocks[:, 1])
    l0 = lattice.ligament_length

    def terms(q: BlockState, bonds: BondGeometry, mat: Material) -> dict:
        r0 = jnp.asarray(lattice.bond_r0, q.dtype)
        q1, q2 = q[b1], q[b2]
        th1, th2 = q1[:, 2], q2[:, 2]
        w1 = q1[:, :2] + _rotate_minus_identity(th1, bonds.arm1)
        w2 = q2[:, :2] + _rotate_minus_identity(th2, bonds.arm2)
        dw = w2 - w1
        bend = th2 - th1
        mean_th = 0.5 * (th1 + th2)
        if linearized:
            strain = (dw[:, 0] * r0[:, 0] + dw[:, 1] * r0[:, 1]) / l0**2
            shear = (r0[:, 0] * dw[:, 1] - r0[:, 1] * dw[:, 0]) / l0**2 - mean_th
        else:
            ell = r0 + dw
            strain = jnp.sqrt(ell[:, 0] ** 2 + ell[:, 1] ** 2) / l0 - 1.0
            # shear angle: from the reference ligament carried by the mean rotation to the current one
            c, s = jnp.cos(mean_th), jnp.sin(mean_th)
            carried = jnp.stack([c * r0[:, 0] - s * r0[:, 1], s * r0[:, 0] + c * r0[:, 1]], axis=-1)
            shear = jnp.arctan2(carried[:, 0] * ell[:, 1] - carried[:, 1] * ell[:, 0],
                                carried[:, 0] * ell[:, 0] + carried[:, 1] * ell[:, 1])
        out = {
            "stretch": 0.5 * mat.k_stretch * (strain * l0) ** 2,
            "shear": 0.5 * mat.k_shear * (shear * l0) ** 2,
            "bend": 0.5 * mat.k_bend * bend**2,
        }
        if use_contact:
            # void angles rotate rigidly with the blocks: alpha1 + (th1 - th2), alpha2 + (th2 - th1)
            a1 = wrap(bonds.void_ref[:, 0] - bend)
            a2 = wrap(bonds.void_ref[:, 1] + bend)
            cf = lambda a: contact_energy(a, mat.k_contact, mat.contact_min, mat.contact_cutoff)  # noqa: E731
            out["contact"] = cf(a1) + cf(a2)
        else:
            out["contact"] = jnp.zeros_like(bend)
        return out

    return terms


def make_energy(lattice: Lattice, *, linearized: bool = False, use_contact: bool = True):
    """Factory: `energy(q [n_blocks, 3], bonds, material) -> total potential energy (mJ)`."""
    terms_fn = make_bond_terms(lattice, linearized=linearized, use_contact=use_contact)

    def energy(q: BlockState, bonds: BondGeometry, mat: Material) -> Scalar:
        t = terms_fn(q, bonds, mat)
        return jnp.sum(t["stretch"] + t["shear"] + t["bend"] + t["contact"])

    return energy


def kinetic_energy(qdot: Float[Array, "... n_blocks 3"], mass, inertia) -> Float[Array, "... n_blocks"]:
    """Per-block kinetic energy 1/2 (m (u'^2 + v'^2) + J theta'^2), mJ (mm/ms velocities, g)."""
    return 0.5 * (mass * (qdot[..., 0] ** 2 + qdot[..., 1] ** 2) + inertia * qdot[..., 2] ** 2)
