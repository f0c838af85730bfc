"""Material and damping parameters, internal units (mm, ms, g; force N, energy mJ).

`Material.paper()` gives the defaults of spec section 10; SI constructors convert on the way in.
"""

import math

import equinox as eqx

from design_engine.lattice import Lattice


class Material(eqx.Module):
    """Ligament, contact, inertia and damping constants (internal units).

    Attributes:
        k_stretch: ligament axial stiffness, N/mm (= g/ms^2).
        k_shear: ligament shear stiffness, N/mm.
        k_bend: ligament bending stiffness, N*mm/rad.
        k_contact: contact stiffness, N*mm/rad.
        contact_min: contact asymptote angle theta_min, rad (< contact_cutoff < 0).
        contact_cutoff: contact onset angle theta_cutoff, rad.
        density: areal density, g/mm^2.
        damping_u: translational damping c_u = c_v, g/ms.
        damping_theta: rotational damping c_theta, g*mm^2/ms.
    """

    k_stretch: float
    k_shear: float
    k_bend: float
    k_contact: float
    contact_min: float
    contact_cutoff: float
    density: float
    damping_u: float
    damping_theta: float

    def __check_init__(self):
        if not (self.contact_min < self.contact_cutoff <= 0.0):
            raise ValueError(
                f"contact angles need theta_min < theta_cutoff <= 0, got {self.contact_min}, "
                f"{self.contact_cutoff} rad"
            )

    @classmethod
    def paper(
        cls,
        lattice: Lattice,
        *,
        damping_ratio: float = 0.0186,
        contact_min_deg: float = -15.0,
        contact_cutoff_deg: float = -10.0,
    ) -> "Material":
        """Spec defaults: k = (120 N/mm, 1.19 N/mm, 1.5 N*mm), rho = 6.18 kg/m^2, zeta = 0.0186.

        Damping is design-independent: derived from zeta and the theta0 = 0 reference unit of the
        lattice kind (spec 6.3).
        """
        k_s, k_b, rho = 1.19, 1.5, 6.18e-3
        s = lattice.spacing
        c_u = 2.0 * damping_ratio * math.sqrt(rho * lattice.unit_area_hat * s**2 * k_s)
        c_t = 2.0 * damping_ratio * math.sqrt(rho * lattice.unit_inertia_hat * s**4 * k_b)
        return cls(
            k_stretch=120.0,
            k_shear=k_s,
            k_bend=k_b,
            k_contact=k_b,
            contact_min=math.radians(contact_min_deg),
            contact_cutoff=math.radians(contact_cutoff_deg),
            density=rho,
            damping_u=c_u,
            damping_theta=c_t,
        )

    def undamped(self) -> "Material":
        """Same material with zero damping."""
        return eqx.tree_at(lambda m: (m.damping_u, m.damping_theta), self, (0.0, 0.0))
