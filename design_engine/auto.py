"""Per-scene choice of integrator and model from measured quantities (speed against accuracy).

The default policy, read off the work-precision charts (README, `metarig bench work-precision`):
- scenes whose voids stay away from the contact barrier (pulse scenes without pre-compression):
  fixed-step velocity Verlet (one force evaluation per step) with a step of
  `safety * 2 / omega_max`, omega_max being the highest natural frequency measured by power
  iteration on the stiffness (Hessian-vector products); float32 (on the chart it changes J by
  1e-5 and the gradient by 3e-3 relative, like float64 Verlet, at 15-20 % less time) and
  nonlinear strains (the linearised strains miss J by tens of percent). The contact terms are left out of the solve and
  every solve checks that all void angles stayed above the contact cutoff at every sample, in
  which case the contact energy was identically zero and the result equals the full model's;
  otherwise the solve is repeated with contact (`needs_contact`, `with_contact`);
- scenes in contact (pre-compressed, or a void that reached the cutoff): adaptive Dopri8 at the
  reference tolerances with contact. The barrier makes the gradient stiff: on the chart fixed
  steps and Dopri5 at the reference tolerances miss it by 4-12 %, Dopri8 stays within 1 %;
- if a fixed-step solve fails (instability), the contact configuration is used instead, and said.
`full_model=True` forces the reference configuration (Dopri5, spec tolerances).
"""

from dataclasses import dataclass

import diffrax

import jax
import jax.numpy as jnp
import numpy as np

from design_engine.dynamics import dof_masses
from design_engine.energy import bond_geometry, make_energy
from design_engine.fixed_step import FixedStepVerlet
from design_engine.geometry import block_geometry
from design_engine.scenes import Scene
from design_engine.simulate import SolverConfig

STABILITY_SAFETY = 0.6  # fraction of the Verlet stability limit 2 / omega_max


@dataclass(frozen=True)
class Choice:
    """A configuration and the reasons it was picked (one line each)."""

    config: SolverConfig
    reasons: tuple[str, ...]
    omega_max: float | None = None  # rad/ms


def make_frequency_estimator(scene: Scene, iterations: int):
    """Factory: jitted `estimate(x, v0, q_base=None) -> (omega_max, v)` for designs `x`
    [n_design] (mm).

    Power iteration on M^-1/2 K M^-1/2 with Hessian-vector products (no dense Hessian:
    `iterations` force-gradient products), started from `v0` [n_free] (unit vector), K taken at
    `q_base` ([n_blocks, 3] mm/rad, contact included; default the reference state, at rest).
    Warm-started from the previous eigenvector, a few dozen iterations track omega_max (rad/ms)
    while an optimiser changes the unit masses. The Rayleigh quotient approaches omega_max from
    below.
    """
    lat, free = scene.lattice, scene.supports.free
    energy = make_energy(lat)
    material = scene.material

    @jax.jit
    def estimate_at(x, v, q_base):
        geom = block_geometry(lat, x)
        bonds = bond_geometry(lat, geom)
        inv_sqrt_m = 1.0 / jnp.sqrt(dof_masses(geom, material)[free])
        q0 = jnp.reshape(q_base, -1).astype(x.dtype)

        def grad_free(qf):
            return jax.grad(lambda z: energy(q0.at[free].set(z).reshape(-1, 3), bonds,
                                             material))(qf)

        def apply(v):
            return inv_sqrt_m * jax.jvp(grad_free, (q0[free],), (inv_sqrt_m * v,))[1]

        def body(_, v):
            w = apply(v)
            return w / jnp.linalg.norm(w)

        v = jax.lax.fori_loop(0, iterations, body, v)
        return jnp.sqrt(jnp.maximum(jnp.dot(v, apply(v)), 0.0)), v

    def estimate(x, v, q_base=None):
        x = jnp.asarray(x)
        return estimate_at(x, v, jnp.zeros(3 * lat.n_blocks, x.dtype) if q_base is None
                           else jnp.asarray(q_base))

    return estimate


def initial_vector(scene: Scene) -> np.ndarray:
    """Seeded random unit start vector [n_free] of the power iteration."""
    v0 = np.random.default_rng(0).normal(size=scene.supports.free.size)
    return v0 / np.linalg.norm(v0)


def max_angular_frequency(scene: Scene, iterations: int = 300, state=None) -> float:
    """Largest omega (rad/ms) of K phi = omega^2 M phi for the scene's design, K taken at
    `state` ([n_blocks, 3] mm/rad; default the reference state at rest).

    Power iteration (see `make_frequency_estimator`): a few hundred force evaluations.
    """
    omega, _ = make_frequency_estimator(scene, iterations)(
        jnp.asarray(scene.design), jnp.asarray(initial_vector(scene)), state)
    return float(omega)


def choose_config(scene: Scene, *, full_model: bool = False,
                  safety: float = STABILITY_SAFETY, omega: float | None = None) -> Choice:
    """Pick the configuration for `scene` (see module docstring).

    `omega` (rad/ms) is a measured highest natural frequency of the scene's design; None
    measures it.
    """
    if full_model:
        return Choice(SolverConfig(), ("forced full model: Dopri5, rtol 1e-8, atol 1e-4, float64, "
                                       "nonlinear strains, contact",))
    if scene.loading.strain > 0.0:
        return Choice(contact_config(), (
            "pre-compression closes voids onto the contact barrier: adaptive Dopri8, rtol 1e-8, "
            "atol 1e-4, with contact (the only method within 1 % of the reference gradient "
            "on the pre-compressed chart)",))
    omega = max_angular_frequency(scene) if omega is None else omega
    dt = safety * 2.0 / omega
    reasons = (
        f"highest natural frequency at rest {omega / (2 * np.pi) * 1e3:.0f} Hz",
        f"fixed-step Verlet, dt = {dt * 1e3:.1f} us = {safety:g} x the stability limit (1 force "
        "evaluation per step; within 0.5 % of J and 1 % of the gradient on the focusing chart)",
        "float32: within 1e-5 of J and 3e-3 of the gradient on the focusing chart",
        "contact terms left out while every void stays above the contact cutoff (checked after "
        "each solve; exact then, else re-solved with contact)",
    )
    config = SolverConfig(solver=FixedStepVerlet(max_dt=dt), use_contact=False, dtype="float32")
    return Choice(config, reasons, omega)


def contact_frequency(min_void_margin: float, material, min_inertia: float) -> float:
    """Upper bound (rad/ms) of the frequency the contact barrier adds at its deepest point.

    At a void angle alpha between the cutoff and the asymptote (tau = (theta_cut - alpha) /
    span in [0, 1)) the barrier's stiffness is d2V/dalpha2 = k_c (1 + 3 tau^2) / (1 - tau^2)^3
    (N mm/rad); two units of rotary inertia >= `min_inertia` (g mm^2) joined by it vibrate at
    most at sqrt(2 d2V/dalpha2 / min_inertia). `min_void_margin` is `Solution.min_void_margin`
    (rad above the asymptote).
    """
    span = float(material.contact_cutoff - material.contact_min)
    tau = min(max((span - float(min_void_margin)) / span, 0.0), 1.0 - 1e-12)
    stiffness = float(material.k_contact) * (1.0 + 3.0 * tau**2) / (1.0 - tau**2) ** 3
    return float(np.sqrt(2.0 * stiffness / min_inertia))


def contact_config() -> SolverConfig:
    """Configuration for scenes in contact: Dopri8 at the reference tolerances, with contact."""
    return SolverConfig(solver=diffrax.Dopri8())


def needs_contact(config: SolverConfig, min_void_margin: float, scene: Scene) -> bool:
    """True if a solve without contact let a void angle reach the contact cutoff (so its result
    differs from the full model's and must be recomputed with contact)."""
    span = scene.material.contact_cutoff - scene.material.contact_min
    return (not config.use_contact) and float(min_void_margin) < span


def with_contact(config: SolverConfig) -> SolverConfig:
    """Configuration for a scene whose voids reached the contact cutoff."""
    return contact_config()


def fallback_config() -> tuple[SolverConfig, str]:
    """The configuration used when a fixed-step solve fails, and why."""
    return contact_config(), ("the fixed-step solve failed (contact stiffening or instability): "
                              "fell back to adaptive Dopri8 at the reference tolerances")
