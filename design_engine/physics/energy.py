"""Potential energy of the network: bond kinematics, scalar per-bond laws, and the bond map.

Three layers, as a scalar law is kept apart from the map that lifts it over a system:
- kinematics: `make_bond_measures` turns the block state into the deformation measures of every
  bond (axial strain, shear angle, relative rotation, current void angles), computed once;
- laws: plain functions `law(measures, material) -> {term name: [n_bonds] energy}` of those
  measures and their material fields (`ligament_law`, spec 5.1; `contact_law`, spec 5.3);
- the bond map: `make_bond_terms` / `make_energy` evaluate the measures and call the laws.
A model (`Model`) is the set of laws: a ligament law, a contact law and any extra terms. A new
law is one such function (plus the `Material` fields it reads) in a `Model`, which a `Scene`
carries (`Scene.model`) to the simulator, the statics, the modal analysis, the calibration and
the solver policy (whose contact frequency is the law's own second derivative:
`void_stiffness`).

Energies in mJ, angles rad, lengths mm. This module writes no force by hand: the dynamics take
`jax.grad` of `make_energy(...)`. The one hand-written force is the default model's in
`physics.native` (C++ custom calls, for speed), tested against the gradient of this energy.
"""

import functools
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from design_engine._types import Array, BlockState, Float, Scalar
from design_engine.physics.angles import atan2, bond_angles
from design_engine.physics.geometry import BlockGeometry
from design_engine.physics.lattice import Lattice
from design_engine.physics.material import Material

PI = jnp.pi

BondTerms = dict[str, Float[Array, " n_bonds"]]  # term name -> per-bond energy, mJ


def wrap(phi):
    """Map angles onto [-pi, pi) (by floor: XLA's CPU float remainder, `jnp.mod`, cost 12 us
    per force evaluation on 1456 void angles, this 0.3 us)."""
    return phi - 2.0 * PI * jnp.floor((phi + PI) / (2.0 * PI))


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


# --- kinematics ----------------------------------------------------------------------------


class BondMeasures(eqx.Module):
    """Deformation measures of every bond (spec 5.1-5.3), the only input of the laws.

    Attributes:
        strain: [n_bonds] axial strain |l| / l0 - 1 (or its linearisation, spec 5.2).
        shear: [n_bonds] shear angle psi, rad: current ligament against the reference one carried
            by the mean rotation of the two units, wrapped to (-pi, pi].
        bend: [n_bonds] relative rotation theta_2 - theta_1, rad (not wrapped).
        voids: [n_bonds, 2] current void angles (alpha1, alpha2), rad, wrapped to [-pi, pi).
        rest_length: ligament rest length l0, mm.
    """

    strain: Float[Array, " n_bonds"]
    shear: Float[Array, " n_bonds"]
    bend: Float[Array, " n_bonds"]
    voids: Float[Array, "n_bonds 2"]
    rest_length: float = eqx.field(static=True)


def void_angles(void_ref: Float[Array, "n_bonds 2"],
                bend: Float[Array, "*batch n_bonds"]) -> Float[Array, "*batch n_bonds 2"]:
    """Void angles (alpha1, alpha2) after a relative rotation `bend`, rad, not wrapped.

    The units are rigid, so the voids turn with them: alpha1 - bend, alpha2 + bend.
    """
    return void_ref + jnp.stack([-bend, bend], axis=-1)


VOID_WRAP = np.pi / 3.0  # reference void angles are taken on [-VOID_WRAP, 2 pi - VOID_WRAP)


def followed_voids(void_ref, q, bond_blocks):
    """[..., n_bonds, 2] void angles (rad) of states q [..., n_blocks, 3], followed continuously
    from the reference angles `void_ref` [n_bonds, 2] (`BondGeometry.void_ref`).

    The reference angle (signed, in (-pi, pi]) is first put on [-60, 300) deg so that a wide
    void (> 180 deg, which the contact law sees as far below theta_min) is not mistaken for a
    unit that passed through the barrier (a feasible design has reference voids in [0, 300]
    deg)."""
    bb = np.asarray(bond_blocks)
    ref = jnp.mod(void_ref + VOID_WRAP, 2.0 * jnp.pi) - VOID_WRAP
    return void_angles(ref, q[..., bb[:, 1], 2] - q[..., bb[:, 0], 2])


def _node(u, v, half_cos, half_sin, arm_x, arm_y):
    """The x and y of a bond's node, mm: the unit's displacement (u, v) plus (R(theta) - I) arm,
    from cos and sin of theta / 2 (cos theta - 1 = -2 sin^2(theta / 2), sin theta =
    2 sin(theta / 2) cos(theta / 2)); every argument [n_bonds]."""
    c1, s = -2.0 * half_sin**2, 2.0 * half_sin * half_cos
    return u + c1 * arm_x - s * arm_y, v + s * arm_x + c1 * arm_y


def make_bond_measures(lattice: Lattice, *, linearized: bool = False):
    """Factory: `measures(q [n_blocks, 3], bonds) -> BondMeasures` (u mm, v mm, theta rad).

    `linearized` uses the small-rotation strain and shear of spec 5.2.

    Written on one [n_bonds] vector per component, gathered one component at a time (a
    structure of arrays): on the 24x16 lattice a force evaluation with contact took 67 us
    against 86-88 us with [n_bonds, 2] vectors and [n_bonds, 3] rows, and its reverse (the
    Hessian product a fixed step's reverse pass takes) 141-145 us against 169-171 us
    (`benchmarks/bench_force_pieces.py`, bench_force_pieces_soa_{before,after}_{1,2}.json).
    """
    b1 = np.asarray(lattice.bond_blocks[:, 0])
    b2 = np.asarray(lattice.bond_blocks[:, 1])
    l0 = lattice.ligament_length

    def measures(q: BlockState, bonds: BondGeometry) -> BondMeasures:
        r0x = jnp.asarray(lattice.bond_r0[:, 0], q.dtype)
        r0y = jnp.asarray(lattice.bond_r0[:, 1], q.dtype)
        u, v, th = q[:, 0], q[:, 1], q[:, 2]
        # the sines and cosines once per unit, of half its rotation: both ends' rotations and
        # the bond's mean rotation follow from them by products (per bond, XLA recomputed the
        # rotations in several fusions: 26 of a force evaluation's 27 transcendentals per bond,
        # benchmarks/bench_contact_step.py --profile)
        half_cos, half_sin = jnp.cos(0.5 * th), jnp.sin(0.5 * th)
        hc1, hs1, hc2, hs2 = half_cos[b1], half_sin[b1], half_cos[b2], half_sin[b2]
        th1, th2 = th[b1], th[b2]
        w1x, w1y = _node(u[b1], v[b1], hc1, hs1, bonds.arm1[:, 0], bonds.arm1[:, 1])
        w2x, w2y = _node(u[b2], v[b2], hc2, hs2, bonds.arm2[:, 0], bonds.arm2[:, 1])
        dwx, dwy = w2x - w1x, w2y - w1y
        bend = th2 - th1
        if linearized:
            strain = (dwx * r0x + dwy * r0y) / l0**2
            shear = (r0x * dwy - r0y * dwx) / l0**2 - 0.5 * (th1 + th2)
        else:
            ex, ey = r0x + dwx, r0y + dwy
            strain = jnp.sqrt(ex**2 + ey**2) / l0 - 1.0
            # shear angle: from the reference ligament carried by the mean rotation to the current one
            c, s = hc1 * hc2 - hs1 * hs2, hs1 * hc2 + hc1 * hs2  # cos, sin of the mean rotation
            cx, cy = c * r0x - s * r0y, s * r0x + c * r0y
            shear = atan2(cx * ey - cy * ex, cx * ex + cy * ey)
        return BondMeasures(strain=strain, shear=shear, bend=bend,
                            voids=wrap(void_angles(bonds.void_ref, bend)), rest_length=l0)

    return measures


# --- laws: (measures, material) -> named per-bond energies ---------------------------------


def ligament_law(m: BondMeasures, mat: Material) -> BondTerms:
    """Ligament energy (spec 5.1), mJ per bond, by part:
    stretch 1/2 k_stretch (eps l0)^2, shear 1/2 k_shear (psi l0)^2, bend 1/2 k_bend dtheta^2.

    Reads `mat.k_stretch` (N/mm), `mat.k_shear` (N/mm), `mat.k_bend` (N mm/rad).
    """
    l0 = m.rest_length
    return {
        "stretch": 0.5 * mat.k_stretch * (m.strain * l0) ** 2,
        "shear": 0.5 * mat.k_shear * (m.shear * l0) ** 2,
        "bend": 0.5 * mat.k_bend * m.bend**2,
    }


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


def contact_law(m: BondMeasures, mat: Material) -> BondTerms:
    """Contact energy (spec 5.3), mJ per bond: the barrier of both void angles.

    Reads `mat.k_contact` (N mm/rad), `mat.contact_min`, `mat.contact_cutoff` (rad).
    """
    def barrier(alpha):
        return contact_energy(alpha, mat.k_contact, mat.contact_min, mat.contact_cutoff)

    return {"contact": barrier(m.voids[:, 0]) + barrier(m.voids[:, 1])}


def no_contact_law(m: BondMeasures, mat: Material) -> BondTerms:
    """Contact switched off (`use_contact=False`): the contact term is reported as zero."""
    return {"contact": jnp.zeros_like(m.bend)}


BondLaw = Callable[[BondMeasures, Material], BondTerms]


@dataclass(frozen=True)
class Model:
    """The energy model: which law gives each part of a bond's energy (one value, hashable, so
    compiled programs are kept per model).

    Attributes:
        ligament: the ligament law (spec 5.1).
        contact: the contact law (spec 5.3); a solve without contact (`use_contact=False`, the
            policy's first try) replaces it by `no_contact_law`.
        extra: further laws whose terms are added (their term names must be new).
    """

    ligament: BondLaw = ligament_law
    contact: BondLaw = contact_law
    extra: tuple[BondLaw, ...] = ()

    def laws(self, use_contact: bool = True) -> tuple[BondLaw, ...]:
        """The laws of a solve with or without the contact terms."""
        return (self.ligament, self.contact if use_contact else no_contact_law, *self.extra)


DEFAULT_MODEL = Model()  # spec 5: ligament law plus contact barrier


def void_stiffness(model: Model, material: Material, alpha) -> float:
    """Second derivative (N mm/rad) of the model's energy of one bond with respect to one void
    angle at `alpha` (rad), every other measure at rest: the stiffness the contact law adds as
    a void closes (for the default law k_c (1 + 3 tau^2) / (1 - tau^2)^3). Differentiated, not
    written out, so that any contact law reaches the solver policy (`policy.contact_frequency`)."""
    return float(_void_stiffness_program(model)(jnp.asarray(alpha, jnp.float64), material))


@functools.cache
def _void_stiffness_program(model: Model):
    """Compiled d2E/dalpha2 (alpha, material) of `void_stiffness`, one per model (the policy asks
    for it after every fixed-step solve with contact)."""

    def energy(a, material):
        zero = jnp.zeros(1)
        far = jnp.full(1, material.contact_cutoff + 1.0)  # the other void: wide open
        m = BondMeasures(strain=zero, shear=zero, bend=zero,
                         voids=jnp.stack([jnp.reshape(a, 1), far], axis=1), rest_length=1.0)
        return sum(jnp.sum(v) for v in _call_laws(model.laws(True), m, material).values())

    return jax.jit(jax.grad(jax.grad(energy)))


def _call_laws(laws, m: BondMeasures, mat: Material) -> BondTerms:
    out: BondTerms = {}
    for law in laws:
        part = law(m, mat)
        if out.keys() & part.keys():
            raise ValueError(f"two laws define the terms {sorted(out.keys() & part.keys())}")
        out.update(part)
    return out


# --- the bond map ---------------------------------------------------------------------------


def make_bond_terms(lattice: Lattice, *, linearized: bool = False, use_contact: bool = True,
                    model: Model = DEFAULT_MODEL):
    """Factory: `terms(q, bonds, material) -> dict` of per-bond energies (mJ), each [n_bonds].

    The measures are computed once and every law of `model` is called on them; the keys are
    the laws' term names, in law order (default: stretch, shear, bend, contact). `q` is
    [n_blocks, 3] (u mm, v mm, theta rad).
    """
    measures_fn = make_bond_measures(lattice, linearized=linearized)
    laws = model.laws(use_contact)

    def terms(q: BlockState, bonds: BondGeometry, mat: Material) -> BondTerms:
        return _call_laws(laws, measures_fn(q, bonds), mat)

    return terms


def make_energy(lattice: Lattice, *, linearized: bool = False, use_contact: bool = True,
                model: Model = DEFAULT_MODEL):
    """Factory: `energy(q [n_blocks, 3], bonds, material) -> total potential energy (mJ)`.

    The sum over bonds of every term of `make_bond_terms` (same arguments).
    """
    terms_fn = make_bond_terms(lattice, linearized=linearized, use_contact=use_contact,
                               model=model)

    def energy(q: BlockState, bonds: BondGeometry, mat: Material) -> Scalar:
        per_bond = None
        for value in terms_fn(q, bonds, mat).values():
            per_bond = value if per_bond is None else per_bond + value
        return jnp.sum(per_bond)

    return energy


class Force(NamedTuple):
    """A force in two parts, so that what it reads of the design and the material is prepared
    once per solve, outside the time loop (and its reverse summed once, after it):
    `pack(bonds, material, dtype) -> packed` and `evaluate(q, packed) -> (energy, dE/dq)`.
    Called as `force(q, bonds, material)` it does both."""

    pack: Callable
    evaluate: Callable

    def __call__(self, q, bonds, material):
        return self.evaluate(q, self.pack(bonds, material, q.dtype))


def jax_force(energy_fn) -> Force:
    """The `Force` of `energy_fn(q, bonds, material)` by JAX's gradient (nothing to pack)."""
    grad = jax.value_and_grad(energy_fn)
    return Force(pack=lambda bonds, material, dtype: (bonds, material),
                 evaluate=lambda q, packed: grad(q, *packed))


def make_contact_energy(lattice: Lattice, model: Model = DEFAULT_MODEL, order=None):
    """Factory: `energy(theta [n_blocks], bonds, material) -> contact energy (mJ)` from the
    units' rotations alone (rad), for a solver that steps the contact terms apart from the rest
    (`fixed_step.FixedStepVerlet.contact_substeps`). `order`: [n_blocks] where unit k's
    rotation sits in `theta` (default: unit k's at k), so that a caller holding the rotations
    in another order (the solver: free ones, then prescribed ones) hands them over as they are:
    each bond reads its units' rotations by one gather, and the gradient sums them back by one
    scatter-add per end, where reordering first cost a third of each (a serial loop on XLA's
    CPU backend, run four times a step by the contact substeps).

    The units are rigid, so a void angle turns with the relative rotation of its two units only
    (`void_angles`): no translation and no transcendental per bond is needed, and 1-D gathers
    of the rotations keep the reverse pass a cheap segment sum. The contact law gets measures
    whose strain and shear are NaN, so a contact law that read them would make the solve fail
    loudly rather than step a wrong force.
    """
    b1 = np.asarray(lattice.bond_blocks[:, 0])
    b2 = np.asarray(lattice.bond_blocks[:, 1])
    if order is not None:
        b1, b2 = np.asarray(order)[b1], np.asarray(order)[b2]

    def energy(theta, bonds: BondGeometry, mat: Material) -> Scalar:
        bend = theta[b2] - theta[b1]
        unknown = jnp.full_like(bend, jnp.nan)
        m = BondMeasures(strain=unknown, shear=unknown, bend=bend,
                         voids=wrap(void_angles(bonds.void_ref, bend)),
                         rest_length=lattice.ligament_length)
        return sum(jnp.sum(v) for v in model.contact(m, mat).values())

    return energy


def kinetic_energy(qdot: Float[Array, "... n_blocks 3"], mass, inertia) -> Float[Array, "... n_blocks"]:
    """Per-block kinetic energy 1/2 (m (u'^2 + v'^2) + J theta'^2), mJ (mm/ms velocities, g)."""
    return 0.5 * (mass * (qdot[..., 0] ** 2 + qdot[..., 1] ** 2) + inertia * qdot[..., 2] ** 2)
