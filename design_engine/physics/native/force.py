"""The native bond force as a JAX function: `make_energy_and_gradient(lattice)`.

The same energy as `energy.make_energy` with the default model (nonlinear ligament law and
contact barrier), and its gradient, computed by the custom calls of `bond_force.cc`; reverse
differentiable to any order the fixed-step solves take (a custom VJP whose backward pass is the
Hessian-vector product and its derivative with respect to the bond geometry and the material,
also a custom call). Forward-mode differentiation is not defined: the statics, the calibration's
Jacobians and the implicit step keep the JAX energy.
"""

import jax
import jax.numpy as jnp
import numpy as np

from design_engine.physics.lattice import Lattice
from design_engine.physics.native.build import library

# the material's fields in the order of the kernel's two [n_bonds, 3] material arrays
LIGAMENT_FIELDS = ("k_stretch", "k_shear", "k_bend")
CONTACT_FIELDS = ("k_contact", "contact_min", "contact_cutoff")


def make_energy_and_gradient(lattice: Lattice, *, use_contact: bool = True):
    """Factory: `fn(q [n_blocks, 3], bonds, material) -> (energy mJ, dE/dq [n_blocks, 3])`.

    Builds and registers the custom calls on first use; raises `build.NativeUnavailable` (one
    line) where they cannot be had. Material fields may be scalars or [n_bonds] arrays.
    """
    library()
    b1 = np.ascontiguousarray(lattice.bond_blocks[:, 0], np.int32)
    b2 = np.ascontiguousarray(lattice.bond_blocks[:, 1], np.int32)
    n = b1.size
    attrs = {"l0": np.float64(lattice.ligament_length), "contact": np.int32(bool(use_contact))}

    def suffix(dtype):
        if dtype == jnp.float64:
            return "f64"
        if dtype == jnp.float32:
            return "f32"
        raise TypeError(f"the native bond force takes float32 or float64 states, not {dtype}")

    def r0(dtype):
        return jnp.asarray(np.ascontiguousarray(lattice.bond_r0), dtype)

    @jax.custom_vjp
    def core(q, arms, vref, lig, con):
        call = jax.ffi.ffi_call(
            f"metarig_bond_force_{suffix(q.dtype)}",
            (jax.ShapeDtypeStruct((), q.dtype), jax.ShapeDtypeStruct(q.shape, q.dtype)),
            vmap_method="sequential")
        return call(b1, b2, q, arms, vref, r0(q.dtype), lig, con, **attrs)

    def forward(*inputs):
        return core(*inputs), inputs

    def backward(inputs, cotangents):
        q, arms, vref, lig, con = inputs
        ebar, gbar = cotangents
        call = jax.ffi.ffi_call(
            f"metarig_bond_force_vjp_{suffix(q.dtype)}",
            tuple(jax.ShapeDtypeStruct(a.shape, q.dtype) for a in inputs),
            vmap_method="sequential")
        return call(b1, b2, q, arms, vref, r0(q.dtype), lig, con, jnp.asarray(ebar, q.dtype),
                    jnp.asarray(gbar, q.dtype), **attrs)

    core.defvjp(forward, backward)

    def energy_and_gradient(q, bonds, material):
        dtype = q.dtype
        arms = jnp.concatenate([bonds.arm1, bonds.arm2], axis=1).astype(dtype)
        vref = bonds.void_ref.astype(dtype)
        lig, con = (jnp.stack([jnp.broadcast_to(jnp.asarray(getattr(material, f), dtype), (n,))
                               for f in fields], axis=1)
                    for fields in (LIGAMENT_FIELDS, CONTACT_FIELDS))
        return core(q, arms, vref, lig, con)

    return energy_and_gradient
