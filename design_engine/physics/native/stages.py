"""The native Verlet stages as a JAX function: `make_verlet_stages(lattice, supports)`.

One step of a fixed-step scheme built of velocity Verlet stages (`solve.fixed_step`: one stage
for Verlet, five for the fourth order) under the default model's force, in one custom call of
`verlet_stages.cc` instead of some 25 XLA kernels a stage. Reverse-mode differentiable by a
custom VJP whose backward pass is a custom call too (it rebuilds the stages from their forces,
kept by the forward pass, and chains the force's Hessian products). The work-energy ledger is
carried through, not differentiated.
"""

import jax
import jax.numpy as jnp
import numpy as np

from design_engine.physics.lattice import Lattice
from design_engine.physics.loading import Supports
from design_engine.physics.native.build import library
from design_engine.physics.native.force import bond_constants, dtype_suffix


def make_verlet_stages(lattice: Lattice, supports: Supports, *, use_contact: bool = True):
    """Factory: `step(q, v, f, ledger, packed, inv_mass, damping, qc, qcd, h) -> (q1, v1, f1,
    ledger1)`, the m stages of one step of `lattice` held by `supports`.

    Args of the returned function:
        q, v, f: [n_free] free state and the force on it at the step's start (mm, rad, mm/ms,
            rad/ms, N, N mm).
        ledger: [6] the work-energy account (`fixed_step.Ledger`'s fields in order).
        packed: the design and material as the native force packs them (`force.
            make_energy_and_gradient(lattice).pack`), prepared once per solve.
        inv_mass, damping: [n_free] diagonals.
        qc, qcd: [m, n_c] the prescribed DOFs' values and velocities at the end of each stage.
        h: [m] the stages' lengths, ms.

    Builds and registers the custom calls on first use; raises `build.NativeUnavailable` (one
    line) where they cannot be had.
    """
    library()
    b1, b2, r0 = bond_constants(lattice)
    # every global DOF's index in [q_free, q_prescribed] (`dynamics.make_full_state`)
    slot = np.ascontiguousarray(supports.assemble_index, np.int32)
    attrs = {"l0": np.float64(lattice.ligament_length), "contact": np.int32(bool(use_contact))}

    def constants(dtype):
        return b1, b2, jnp.asarray(r0, dtype), slot

    def call(inputs):
        q = inputs[0]
        out = jax.ffi.ffi_call(
            f"metarig_verlet_stages_{dtype_suffix(q.dtype)}",
            (jax.ShapeDtypeStruct(q.shape, q.dtype), jax.ShapeDtypeStruct(q.shape, q.dtype),
             jax.ShapeDtypeStruct((6,), q.dtype),
             jax.ShapeDtypeStruct(inputs[11].shape + q.shape, q.dtype)),  # h: [m]
            vmap_method="sequential")
        return out(*constants(q.dtype), *inputs, **attrs)

    # inputs: q, v, f, arms, vref, lig, con, inv_mass, damping, qc, qcd, h, ledger
    @jax.custom_vjp
    def core(*inputs):
        q1, v1, led1, fs = call(inputs)
        return q1, v1, fs[-1], led1

    def forward(*inputs):
        q1, v1, led1, fs = call(inputs)
        return (q1, v1, fs[-1], led1), (inputs, fs)

    def backward(residuals, cotangents):
        inputs, fs = residuals
        qb1, vb1, fb1, _ = cotangents
        q = inputs[0]
        out = jax.ffi.ffi_call(
            f"metarig_verlet_stages_vjp_{dtype_suffix(q.dtype)}",
            tuple(jax.ShapeDtypeStruct(a.shape, q.dtype) for a in inputs[:10]),
            vmap_method="sequential")
        grads = out(*constants(q.dtype), *inputs, fs, qb1, vb1, fb1, **attrs)
        return (*grads, *(jnp.zeros_like(a) for a in inputs[10:]))

    core.defvjp(forward, backward)

    def step(q, v, f, ledger, packed, inv_mass, damping, qc, qcd, h):
        return core(q, v, f, *packed, inv_mass, damping, qc, qcd, h, ledger)

    return step
