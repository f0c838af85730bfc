"""Equations of motion M q_f'' = -dV/dq_f - C q_f' (spec 6), as a pure right-hand side.

The integrated state is y = [q_f, p_f] (flat, [2 n_free]) with p_f = velocity_scale * q_f'.
With velocity_scale = 1e3 the velocity half is in mm/s, the units of the reference solver's
error control: the same absolute tolerance then means the same thing for positions (mm) and
velocities (mm/s) while time runs in ms.
"""

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from design_engine._types import Array, Float
from design_engine.physics.energy import BondGeometry, Force, bond_geometry
from design_engine.physics.geometry import BlockGeometry
from design_engine.physics.lattice import Lattice
from design_engine.physics.loading import Loading, Supports, make_prescribed
from design_engine.physics.material import Material

VELOCITY_SCALE = 1.0e3


class DynamicsArgs(eqx.Module):
    """Differentiable inputs of the right-hand side (one design, one load case).

    Attributes:
        bonds: per-bond geometry of the design.
        material: material constants.
        loading: input/stage signals.
        inv_mass: [n_free] inverse mass (1/g) or inverse rotary inertia (1/(g mm^2)) per free DOF.
        damping: [n_free] viscous coefficient per free DOF (g/ms or g mm^2/ms).
    """

    bonds: BondGeometry
    material: Material
    loading: Loading
    inv_mass: Float[Array, " n_free"]
    damping: Float[Array, " n_free"]


def dof_masses(geom: BlockGeometry, mat: Material) -> Float[Array, " n_dof"]:
    """[3 n_blocks] mass per global DOF: (m_b, m_b, J_b) with m = rho A, J = rho I_p."""
    m = mat.density * geom.areas
    j = mat.density * geom.polar_moments
    return jnp.stack([m, m, j], axis=-1).reshape(-1)


def dof_damping(n_blocks: int, mat: Material) -> Float[Array, " n_dof"]:
    """[3 n_blocks] damping per global DOF (design-independent, spec 6.3): (c_u, c_u, c_theta)
    of every block, from scalar coefficients or from one per block ([n_blocks], a specimen's
    true material)."""
    c_u = jnp.broadcast_to(jnp.asarray(mat.damping_u), (n_blocks,))
    c_t = jnp.broadcast_to(jnp.asarray(mat.damping_theta), (n_blocks,))
    return jnp.stack([c_u, c_u, c_t], axis=-1).reshape(-1)


def make_dynamics_args(lattice: Lattice, supports: Supports, geom: BlockGeometry, mat: Material,
                       loading: Loading) -> DynamicsArgs:
    """Assemble the RHS inputs for one design (differentiable in `geom`)."""
    free = supports.free
    return DynamicsArgs(
        bonds=bond_geometry(lattice, geom),
        material=mat,
        loading=loading,
        inv_mass=1.0 / dof_masses(geom, mat)[free],
        damping=dof_damping(lattice.n_blocks, mat)[free],
    )


def make_full_state(supports: Supports):
    """Factory: `full(q_f, t, loading) -> q [n_blocks, 3]` with prescribed DOFs filled in."""
    values, _ = make_prescribed(supports)
    index = np.asarray(supports.assemble_index)
    nb = supports.n_blocks

    def full(q_f, t, loading: Loading):
        return jnp.concatenate([q_f, values(t, loading)])[index].reshape(nb, 3)

    return full


def make_rhs(supports: Supports, force: Force, velocity_scale: float = VELOCITY_SCALE):
    """Factory: `rhs(t, y, (args, packed))` for diffrax, y = [q_f, velocity_scale * q_f']
    ([2 n_free]); `force` an `energy.Force` (JAX's gradient of an energy, or the native force),
    `packed` its `force.pack(args.bonds, args.material, dtype)`, prepared once per solve."""
    full = make_full_state(supports)
    n_free = int(supports.free.size)
    free = np.asarray(supports.free)

    def rhs(t, y, args_packed):
        args, packed = args_packed
        q_f, p_f = y[:n_free], y[n_free:]
        v_f = p_f / velocity_scale
        _, grad_all = force.evaluate(full(q_f, t, args.loading), packed)
        grad = grad_all.reshape(-1)[free]
        acc = args.inv_mass * (-grad - args.damping * v_f)
        return jnp.concatenate([v_f, velocity_scale * acc])

    return rhs
