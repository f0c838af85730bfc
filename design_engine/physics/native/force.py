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


def dtype_suffix(dtype) -> str:
    """The custom calls' name suffix of a state's dtype."""
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


def _custom_call(name: str, constants, attrs=None):
    """`core(x, *params) -> (energy, dE/dx)` by the custom call `metarig_<name>_<f32|f64>`,
    reverse differentiable by `metarig_<name>_vjp_<...>` (the cotangents of x and every param).
    Both calls take `constants(dtype)` (the lattice's, not differentiated) first, then x and
    the params, and the vjp call the energy's and gradient's cotangents last."""
    attrs = attrs or {}

    @jax.custom_vjp
    def core(x, *params):
        call = jax.ffi.ffi_call(
            f"metarig_{name}_{dtype_suffix(x.dtype)}",
            (jax.ShapeDtypeStruct((), x.dtype), jax.ShapeDtypeStruct(x.shape, x.dtype)),
            vmap_method="sequential")
        return call(*constants(x.dtype), x, *params, **attrs)

    def forward(*inputs):
        return core(*inputs), inputs

    def backward(inputs, cotangents):
        x = inputs[0]
        ebar, gbar = cotangents
        call = jax.ffi.ffi_call(
            f"metarig_{name}_vjp_{dtype_suffix(x.dtype)}",
            tuple(jax.ShapeDtypeStruct(a.shape, x.dtype) for a in inputs),
            vmap_method="sequential")
        return call(*constants(x.dtype), *inputs, jnp.asarray(ebar, x.dtype),
                    jnp.asarray(gbar, x.dtype), **attrs)

    core.defvjp(forward, backward)
    return core


def bond_constants(lattice: Lattice):
    """(b1, b2 [n_bonds] int32, r0 [n_bonds, 2]): the lattice's constants every bond-map call
    takes first (the units each bond joins, its rest vector)."""
    return (np.ascontiguousarray(lattice.bond_blocks[:, 0], np.int32),
            np.ascontiguousarray(lattice.bond_blocks[:, 1], np.int32),
            np.ascontiguousarray(lattice.bond_r0))


def make_energy_and_gradient(lattice: Lattice, *, use_contact: bool = True) -> Force:
    """Factory: the `energy.Force` `fn(q [n_blocks, 3], bonds, material) -> (energy mJ, dE/dq
    [n_blocks, 3])`, packing the bond geometry and material into the kernel's arrays.

    Builds and registers the custom calls on first use; raises `build.NativeUnavailable` (one
    line) where they cannot be had. Material fields may be scalars or [n_bonds] arrays.
    """
    library()
    b1, b2, r0 = bond_constants(lattice)
    n = b1.size
    core = _custom_call("bond_force", lambda dtype: (b1, b2, jnp.asarray(r0, dtype)),
                        {"l0": np.float64(lattice.ligament_length),
                         "contact": np.int32(bool(use_contact))})

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
    core = _custom_call("contact_force", lambda dtype: (b1, b2))

    def pack(bonds, material, dtype):
        return bonds.void_ref.astype(dtype), _per_bond(material, CONTACT_FIELDS, n, dtype)

    return Force(pack=pack, evaluate=lambda theta, packed: core(theta, *packed))
