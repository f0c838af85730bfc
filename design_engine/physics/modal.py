"""Linear modal analysis about a (possibly pre-stressed) state: K phi = omega^2 M phi (spec 11.9).

K is the Hessian of the potential with respect to the free DOFs (contact included), with the
prescribed DOFs held at their values in the given state; M is the diagonal mass matrix.
"""

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg

from design_engine.physics.dynamics import dof_masses
from design_engine.physics.energy import bond_geometry, make_energy
from design_engine.physics.geometry import block_geometry
from design_engine.physics.scenes import Scene


@dataclass(frozen=True)
class Modes:
    """Natural modes of a scene.

    Attributes:
        frequencies_hz: [n_free] natural frequencies, ascending, Hz.
        shapes: [n_free, n_free] mass-normalised mode shapes (columns) on the free DOFs.
        free: [n_free] global DOF ids of the free DOFs.
        stiffness: [n_free, n_free] stiffness matrix (internal units).
        masses: [n_free] diagonal mass per free DOF (g, g mm^2).
    """

    frequencies_hz: np.ndarray
    shapes: np.ndarray
    free: np.ndarray
    stiffness: np.ndarray
    masses: np.ndarray


def modal_analysis(scene: Scene, q_state: np.ndarray | None = None, *, linearized: bool = False,
                   use_contact: bool = True) -> Modes:
    """Natural frequencies and modes of `scene` linearised about `q_state` ([n_blocks, 3], internal
    units: mm, rad; default the reference state)."""
    lat, sup = scene.lattice, scene.supports
    free = sup.free
    geom = block_geometry(lat, jnp.asarray(scene.design))
    bonds = bond_geometry(lat, geom)
    energy = make_energy(lat, linearized=linearized, use_contact=use_contact, model=scene.model)
    q0 = jnp.zeros(3 * lat.n_blocks) if q_state is None else jnp.asarray(q_state).reshape(-1)

    def v_free(qf):
        return energy(q0.at[free].set(qf).reshape(-1, 3), bonds, scene.material)

    k = np.asarray(jax.jit(jax.hessian(v_free))(q0[free]))
    k = 0.5 * (k + k.T)
    m = np.asarray(dof_masses(geom, scene.material))[free]
    w2, phi = scipy.linalg.eigh(k, np.diag(m))
    # rad/ms -> Hz; tiny negative eigenvalues of an unconstrained system are rigid-body modes
    freqs = np.sqrt(np.clip(w2, 0.0, None)) * 1e3 / (2.0 * np.pi)
    return Modes(frequencies_hz=freqs, shapes=phi, free=free, stiffness=k, masses=m)
