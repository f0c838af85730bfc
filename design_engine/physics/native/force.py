"""The native bond force as JAX functions: `make_energy_and_gradient(lattice)`, and the contact
terms alone from the rotations, `make_contact_energy_and_gradient(lattice, order)`.

The same energies as `energy.make_energy` with the default model (nonlinear ligament law and
contact barrier) and `energy.make_contact_energy`, and their gradients, computed by the custom
calls of `bond_force.cc`. Reverse-mode differentiable as the solves need it: a custom VJP whose
backward pass (the Hessian-vector product and its derivative in the bond geometry and the
material) is a custom call too. Forward mode is not defined: the statics, the calibration's
Jacobians and the implicit step keep the JAX energy (`SolverConfig.native_force`).
"""

import jax
import jax.numpy as jnp
import numpy as np

from design_engine.physics.energy import Force
from design_engine.physics.lattice import Lattice
from design_engine.physics.native.build import library


def _suffix(dtype) -> str:
    if dtype == jnp.float64:
        return "f64"
    if dtype == jnp.float32:
        return "f32"
    raise TypeError(f"the native bond force takes float32 or float64 states, not {dtype}")


def _per_bond(material, fields, n: int, dtype):
    """[n, len(fields)] of the material's fields (scalars or [n] arrays)."""
    return jnp.stack([jnp.broadcast_to(jnp.asarray(getattr(material, f), dtype), (n,))
                      for f in fields], axis=1)


# the material's fields in the order of the kernel's two [n_bonds, 3] material arrays
LIGAMENT_FIELDS = ("k_stretch", "k_shear", "k_bend")
CONTACT_FIELDS = ("k_contact", "contact_min", "contact_cutoff")


def make_energy_and_gradient(lattice: Lattice, *, use_contact: bool = True) -> Force:
    """Factory: the `energy.Force` `fn(q [n_blocks, 3], bonds, material) -> (energy mJ, dE/dq
    [n_blocks, 3])`, packing the bond geometry and material into the kernel's arrays.

    Builds and registers the custom calls on first use; raises `build.NativeUnavailable` (one
    line) where they cannot be had. Material fields may be scalars or [n_bonds] arrays.
    """
    library()
    b1 = np.ascontiguousarray(lattice.bond_blocks[:, 0], np.int32)
    b2 = np.ascontiguousarray(lattice.bond_blocks[:, 1], np.int32)
    n = b1.size
    attrs = {"l0": np.float64(lattice.ligament_length), "contact": np.int32(bool(use_contact))}

    def r0(dtype):
        return jnp.asarray(np.ascontiguousarray(lattice.bond_r0), dtype)

    @jax.custom_vjp
    def core(q, arms, vref, lig, con):
        call = jax.ffi.ffi_call(
            f"metarig_bond_force_{_suffix(q.dtype)}",
            (jax.ShapeDtypeStruct((), q.dtype), jax.ShapeDtypeStruct(q.shape, q.dtype)),
            vmap_method="sequential")
        return call(b1, b2, q, arms, vref, r0(q.dtype), lig, con, **attrs)

    def forward(*inputs):
        return core(*inputs), inputs

    def backward(inputs, cotangents):
        q, arms, vref, lig, con = inputs
        ebar, gbar = cotangents
        call = jax.ffi.ffi_call(
            f"metarig_bond_force_vjp_{_suffix(q.dtype)}",
            tuple(jax.ShapeDtypeStruct(a.shape, q.dtype) for a in inputs),
            vmap_method="sequential")
        return call(b1, b2, q, arms, vref, r0(q.dtype), lig, con, jnp.asarray(ebar, q.dtype),
                    jnp.asarray(gbar, q.dtype), **attrs)

    core.defvjp(forward, backward)

    def pack(bonds, material, dtype):
        arms = jnp.concatenate([bonds.arm1, bonds.arm2], axis=1).astype(dtype)
        return (arms, bonds.void_ref.astype(dtype),
                _per_bond(material, LIGAMENT_FIELDS, n, dtype),
                _per_bond(material, CONTACT_FIELDS, n, dtype))

    return Force(pack=pack, evaluate=lambda q, packed: core(q, *packed))


def make_contact_energy_and_gradient(lattice: Lattice, order=None) -> Force:
    """Factory: the `energy.Force` `fn(theta [n_blocks], bonds, material) -> (contact energy mJ,
    dE/dtheta)`, the contact terms alone from the units' rotations (rad), as
    `energy.make_contact_energy` with the same `order` (where unit k's rotation sits in theta)
    and the default contact law."""
    library()
    b1, b2 = lattice.bond_blocks[:, 0], lattice.bond_blocks[:, 1]
    if order is not None:
        b1, b2 = np.asarray(order)[b1], np.asarray(order)[b2]
    b1, b2 = np.ascontiguousarray(b1, np.int32), np.ascontiguousarray(b2, np.int32)
    n = b1.size

    @jax.custom_vjp
    def core(theta, vref, con):
        call = jax.ffi.ffi_call(
            f"metarig_contact_force_{_suffix(theta.dtype)}",
            (jax.ShapeDtypeStruct((), theta.dtype),
             jax.ShapeDtypeStruct(theta.shape, theta.dtype)),
            vmap_method="sequential")
        return call(b1, b2, theta, vref, con)

    def forward(*inputs):
        return core(*inputs), inputs

    def backward(inputs, cotangents):
        theta = inputs[0]
        ebar, gbar = cotangents
        call = jax.ffi.ffi_call(
            f"metarig_contact_force_vjp_{_suffix(theta.dtype)}",
            tuple(jax.ShapeDtypeStruct(a.shape, theta.dtype) for a in inputs),
            vmap_method="sequential")
        return call(b1, b2, *inputs, jnp.asarray(ebar, theta.dtype),
                    jnp.asarray(gbar, theta.dtype))

    core.defvjp(forward, backward)

    def pack(bonds, material, dtype):
        return bonds.void_ref.astype(dtype), _per_bond(material, CONTACT_FIELDS, n, dtype)

    return Force(pack=pack, evaluate=lambda theta, packed: core(theta, *packed))
