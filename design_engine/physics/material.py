"""Material and damping parameters, internal units (mm, ms, g; force N, energy mJ).

`Material.paper()` gives the defaults of spec section 10, read from the default material file
`design_engine/physics/materials/default.toml` (SI); `Material.from_si` converts SI values on the way in.
Material files themselves (format, validation, saving) are `design_engine.physics.material_file`.
"""

import functools
import math
import tomllib
from pathlib import Path

import equinox as eqx

from design_engine.physics.lattice import Lattice

DEFAULT_FILE = Path(__file__).resolve().with_name("materials") / "default.toml"

# SI value -> engine (mm, ms, g) value: engine = SI * 10**power for the linear parameters.
# Exact powers of ten are applied by division or multiplication so that the spec's decimal
# values land on the same floats as the literals.
SI_POWER = {
    "k_stretch": -3,  # N/m -> N/mm
    "k_shear": -3,  # N/m -> N/mm
    "k_bend": 3,  # N m/rad -> N mm/rad
    "k_contact": 3,  # N m/rad -> N mm/rad
    "density": -3,  # kg/m^2 -> g/mm^2
    "damping_u": 0,  # N s/m = kg/s -> g/ms
    "damping_theta": 6,  # N m s = kg m^2/s -> g mm^2/ms
}
_ANGLES = ("contact_min_deg", "contact_cutoff_deg")  # deg -> rad


def si_to_engine(name: str, x):
    """Engine value of the SI value `x` of parameter `name` (float or jax array)."""
    if name in _ANGLES:
        return math.radians(x)
    p = SI_POWER[name]
    return x * 10.0**p if p >= 0 else x / 10.0**-p


def engine_to_si(name: str, x):
    """SI value of the engine value `x` of parameter `name` (float or jax array)."""
    if name in _ANGLES:
        return math.degrees(x)
    p = SI_POWER[name]
    return x / 10.0**p if p >= 0 else x * 10.0**-p


_FIELD = {"contact_min_deg": "contact_min", "contact_cutoff_deg": "contact_cutoff"}


@functools.lru_cache(maxsize=1)
def _default_items() -> tuple[tuple[str, float], ...]:
    with DEFAULT_FILE.open("rb") as f:
        params = tomllib.load(f)["parameters"]
    return tuple((k, float(p["value"] if isinstance(p, dict) else p)) for k, p in params.items())


def default_si() -> dict[str, float]:
    """Values of the default material file, SI (damping as `damping_ratio`)."""
    return dict(_default_items())


def reference_damping(lattice: Lattice, damping_ratio: float, density: float, k_shear: float,
                      k_bend: float) -> tuple[float, float]:
    """Design-independent damping (spec 6.3) from zeta and the lattice's theta0 = 0 reference unit.

    Engine units in and out: density g/mm^2, k_shear N/mm, k_bend N*mm/rad -> (c_u g/ms,
    c_theta g*mm^2/ms). Python floats in, floats out; jax values in (traced), jax values out.
    """
    import jax.numpy as jnp

    sqrt = math.sqrt if all(isinstance(v, (int, float)) for v in
                            (damping_ratio, density, k_shear, k_bend)) else jnp.sqrt
    s = lattice.spacing
    c_u = 2.0 * damping_ratio * sqrt(density * lattice.unit_area_hat * s**2 * k_shear)
    c_t = 2.0 * damping_ratio * sqrt(density * lattice.unit_inertia_hat * s**4 * k_bend)
    return c_u, c_t


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

    A model's material holds one value of each. A sample that differs from its model (the
    simulated rig's truth, `hardware_sim.specimen.imperfect`) may hold one value per bond
    ([n_bonds] arrays, in bond order) for the stiffnesses and one per block ([n_blocks]) for
    the damping: the laws broadcast them over the bonds (`energy.ligament_law`,
    `energy.contact_law`) and `dynamics.dof_damping` over the blocks. Only the simulation
    takes such a material; the design, the statics and the calibration take scalars.
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
    def from_si(cls, values: dict[str, float], lattice: Lattice | None = None) -> "Material":
        """Material from SI values (names and units of `material_file.SI_UNITS`), unchecked.

        Every stiffness, both contact angles (deg) and the density are required. `damping_u` and
        `damping_theta` (N s/m, N m s) are used when given; a missing one is derived from
        `damping_ratio` and `lattice` (spec 6.3) with this material's density and stiffnesses.
        """
        e = {_FIELD.get(k, k): si_to_engine(k, float(values[k])) for k in (*SI_POWER, *_ANGLES)
             if k in values}
        if "damping_u" not in e or "damping_theta" not in e:
            if lattice is None or "damping_ratio" not in values:
                raise ValueError("damping needs damping_u and damping_theta, or damping_ratio and "
                                 "a lattice")
            c_u, c_t = reference_damping(lattice, float(values["damping_ratio"]), e["density"],
                                         e["k_shear"], e["k_bend"])
            e.setdefault("damping_u", c_u)
            e.setdefault("damping_theta", c_t)
        return cls(**e)

    def to_si(self) -> dict[str, float]:
        """SI values (names of `material_file.SI_UNITS`; damping explicit, no ratio)."""
        return {k: float(engine_to_si(k, getattr(self, _FIELD.get(k, k)))) for k in (*SI_POWER, *_ANGLES)}

    @classmethod
    def paper(
        cls,
        lattice: Lattice,
        *,
        damping_ratio: float | None = None,
        contact_min_deg: float | None = None,
        contact_cutoff_deg: float | None = None,
    ) -> "Material":
        """Spec defaults (the default material file): k = (120 N/mm, 1.19 N/mm, 1.5 N*mm),
        rho = 6.18 kg/m^2, zeta = 0.0186, contact -15 / -10 deg; keywords override the file.

        Damping is design-independent: derived from zeta and the theta0 = 0 reference unit of the
        lattice kind (spec 6.3).
        """
        v = default_si()
        if damping_ratio is not None:
            v.pop("damping_u", None)
            v.pop("damping_theta", None)
            v["damping_ratio"] = damping_ratio
        if contact_min_deg is not None:
            v["contact_min_deg"] = contact_min_deg
        if contact_cutoff_deg is not None:
            v["contact_cutoff_deg"] = contact_cutoff_deg
        return cls.from_si(v, lattice)

    def undamped(self) -> "Material":
        """Same material with zero damping."""
        return eqx.tree_at(lambda m: (m.damping_u, m.damping_theta), self, (0.0, 0.0))

    def replaced(self, **fields) -> "Material":
        """Same material with the given fields (engine units; jax values allowed) replaced."""
        if not fields:
            return self
        names = tuple(fields)
        return eqx.tree_at(lambda m: tuple(getattr(m, n) for n in names), self,
                           tuple(fields[n] for n in names))

    def scaled(self, factors: dict[str, float]) -> "Material":
        """Same material with each named field multiplied by its factor."""
        return self.replaced(**{n: getattr(self, n) * f for n, f in factors.items()})
