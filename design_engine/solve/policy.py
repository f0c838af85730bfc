"""Per-scene choice of integrator and model from measured quantities (speed against accuracy).

The default policy, read off the work-precision and speed-up charts (README, `metarig bench`):
- pulse scenes, and pre-compressed scenes with the default static pre-compression (the pulse
  starts from rest in the equilibrium under the closed stages): fixed-step velocity Verlet (one
  force evaluation per step) with a step of `safety * 2 / omega_max`, omega_max being the
  highest natural frequency at the state the pulse starts from (rest, or the static
  equilibrium with its contact stiffness), measured by power iteration (Hessian-vector
  products); float32 (on the charts it changes J by 1e-5 to 1e-4 and the gradient by 3e-3 relative,
  like float64 Verlet, at 20-40 % less time) and nonlinear strains (the linearised strains miss
  J by tens of percent). The contact terms are left out of the solve and every solve checks
  that all void angles stayed above the contact cutoff at every sample, in which case the
  contact energy was identically zero and the result equals the full model's;
- a solve whose voids reached the cutoff is repeated with contact at the same step and
  precision by the fourth-order composition of Verlet steps (`FixedStepVerlet(order=4)`,
  CONTACT_ORDER: five force evaluations a step, the contact forces with the rest; from the
  first solve, in float64 and at STATIC_CONTACT_STEP x the step, when the static equilibrium
  already reaches the cutoff), and that result stands while the solve's work-energy drift
  stays within ENERGY_TOLERANCE (`next_config`) and its objective moves by at most
  STEP_ERROR_TOLERANCE when the same start is solved at COARSE x the step (at Verlet's step
  for STATIC_CONTACT_STEP, that solve standing in its place where its own error passes; the
  driver, for a caller that gives its objective). A drift
  past the tolerance repeats the solve once at REFINE x the step when that is predicted to
  pass, else with adaptive Dopri8 at the reference tolerances with contact. A fixed step with
  contact that failed is repeated once at REFINE x the step (Verlet: with its contact forces
  substepped CONTACT_SUBSTEPS_MAX times), then (as any other failed fixed-step solve) with
  Dopri8. (Verlet with contact, for a caller that asks for it, is also held to h x omega_c <=
  CONTACT_STEP_LIMIT, omega_c the barrier's own frequency at the deepest void,
  `contact_frequency`, by substepping the contact forces, and judged at half its step.) An
  optimiser's next evaluation starts where the last one ended while that was in contact, with a fixed step with
  contact for the rest of the run (a refined step climbing back one halving an evaluation
  toward the chosen step unless its drift predicts a failure), with the fixed step if that was
  Dopri8 (`start_config`);
- the dynamic pre-compression ramp (`precompression="ramp"`, the reference's protocol):
  adaptive Dopri8 at the reference tolerances with contact (the ramp lasts 40-320 ms).
`full_model=True` forces the reference configuration (Dopri5, spec tolerances).
"""

import dataclasses
from dataclasses import dataclass

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

from design_engine.physics.dynamics import dof_masses
from design_engine.physics.energy import (DEFAULT_MODEL, Model, bond_geometry, followed_voids,
                                          make_energy, void_stiffness)
from design_engine.physics.geometry import block_geometry
from design_engine.physics.native.build import available as native_available
from design_engine.physics.scenes import Scene
from design_engine.solve.fixed_step import FixedStepVerlet, is_fixed_step
from design_engine.solve.simulate import SolverConfig, static_state

STABILITY_SAFETY = 0.6  # fraction of the Verlet stability limit 2 / omega_max
# largest dt x omega_c (the contact barrier's own frequency at the deepest void) a Verlet step
# with contact may take (the fourth order's step check judges it instead: `barrier_ratio`):
# with dt x omega_max <= 1.2 it keeps dt x sqrt(omega_max^2 + omega_c^2)
# within 0.8 x the stability limit 2 (measured: 0.45 on the 24x16 focusing design in contact and
# 0.95 on 24x18 at 8 % pre-compression, both within 1e-4 of J)
CONTACT_STEP_LIMIT = 1.0
# largest work-energy drift of a fixed-step solve, relative to the energy it moved
# (`Solution.energy_error`), that the policy accepts (benchmarks/bench_energy_check.py)
ENERGY_TOLERANCE = 1e-4
# a fixed-step solve that these checks reject is re-solved once at REFINE x its step when that
# is predicted to pass (Verlet is second order: the drift falls by REFINE^2, to at most half
# the tolerance; dt x omega_c by REFINE, to at most the limit), else with Dopri8.
# Hypersensitive solves drift far more (8.7e-4 and up on the chart) and go to Dopri8 directly:
# a step small enough to hide their drift would still miss J by up to 100 x the drift
REFINE = 0.5
# the work-energy drift that rounding alone may give a right fixed-step solve, by precision. In
# float32 the ledger, summed over thousands of steps, drifted by 2.2e-6 to 5.8e-5 on the 1 %
# scene's designs of a focus-vs-protect run (the fourth order in contact at 0.5, 1 and 1.5 x the
# step), and by no less at half the step than at the step (more steps, more rounding; J was
# off by up to 5.5e-5 at half the step against 6.3e-6 at the step), where float64 drifted by
# orders of magnitude less and its drift shrank with the step
# (bench_drift_floor_1pct_float32_amd.json, _float64_amd.json). So in float32 any drift the
# balance accepts may be rounding, and predicts nothing of another step (`predicted_drift`)
DRIFT_FLOOR = {"float32": ENERGY_TOLERANCE, "float64": 0.0}
# a fixed step with contact whose only fault is the barrier outgrowing it (its drift within the
# tolerance) keeps its step and steps the contact forces by substeps instead (multiple time
# stepping, `fixed_step.integrate`): the fewest of 2, 4, ... CONTACT_SUBSTEPS_MAX that bring
# (dt / n) x omega_c within CONTACT_STEP_LIMIT. A substep costs the contact terms alone (about
# a tenth of a force evaluation), where halving the step doubled every force evaluation
CONTACT_SUBSTEPS_MAX = 8
# a fixed step takes the contact terms with this many substeps from its first solve with them
# (`with_contact`): none apart, the fourth order steps them with the rest. On a
# focus-vs-protect design at 8 % the fourth order at the policy's step was within 4.3e-9 of J
# with none, 1.5e-5 and 1.4e-5 with 2 and 4 substeps, in 4.3 s against 6.7 and 8.3 s (the
# splitting's own error and cost); on a focusing design and the 1 % scene, within 1.5e-5 and
# 4.6e-8 to 7.3e-6 in 0.4-0.6 x the time of 4 substeps (benchmarks/bench_order4_substeps.py ->
# bench_order4_substeps_{8pct,focusing,1pct}_amd.json). (Verlet entered contact with 4: its
# barrier criterion, CONTACT_STEP_LIMIT, then held at once)
CONTACT_ENTRY_SUBSTEPS = 1
# a fixed-step solve with contact whose voids reached the cutoff, at its start (a static
# pre-compression past it) or under the pulse, is also judged on the objective itself: the
# driver solves the same start at half the step (`driver.solve_with_policy(objective=...)`;
# the fourth order's, CONTACT_ORDER, at COARSE x the step, below), and a J that moves by more
# than this (x 4/3, Richardson: the error of the whole step) does not stand. Verlet's
# half-step solve is then judged
# at its own half when the quarter of the step is predicted to pass (`after_half_step`): it
# stands when its own estimate passes; else the quarter-step solve stands when its error by
# that pair (a quarter of it) passes and the two changes shrink as a second-order step's
# (by at least STEP_CONVERGENCE_MIN, 4 in theory: `after_quarter_step`); else Dopri8. The
# judging solves are the candidates: none is solved twice. On such designs the work-energy
# balance does not bound J: on the focus-vs-protect run's designs at 8 % the policy's step
# missed J by 6.2e-4 and 1.1e-3 at drifts of 3.0e-5 and 2.5e-5 (`benchmarks/bench_outer_step.py`);
# where this estimate accepts, it was within 0.6-1.7x of the true error, and where the step was
# not yet converging (a half-step change larger than the whole step's) it fell 3.8x short
# (`benchmarks/bench_step_convergence.py`). Under the pulse, on a focus-vs-protect front's 1 %
# scene, four of eight solves that the balance let stand were 2.6e-4 to 9.7e-4 off J, and
# this estimate was 0.75-1.5x their error (README, "Contact under the pulse")
STEP_ERROR_TOLERANCE = 1e-4
STEP_CONVERGENCE_MIN = 2.0
# a fixed step with contact goes by the fourth-order composition of Verlet steps
# (`FixedStepVerlet(order=4)`, five force evaluations a step) at the step Verlet would take
# (`with_contact`). Verlet's own gradient converges slowly in contact: on designs where the
# pulse reaches the cutoff (a focusing run's evaluation 13, a focus-vs-protect run's 1 % scene)
# Verlet at the policy's step gave cosines of 0.99987-0.99997 against Dopri8 at rtol 1e-10,
# halving the step did not always help (0.99993 -> 0.99987), and float64 gave the same
# (README, "Evaluation 13's gradient"), where the fourth order at the same step gave
# 0.9999998-1.0000000 with J within 4.6e-8 (float64) to 1.5e-5 (float32) in 1.9-2.1 x
# Verlet's time with one contact substep (benchmarks/bench_order4_substeps.py ->
# bench_order4_substeps_{1pct,focusing,8pct}_amd.json). In deep static contact (8 %) it was
# within 4.3e-9 to 1.1e-7 of J, cosine 1.0000000, where Verlet at the step missed J by 3.0e-4
# to 3.0e-3 with cosines down to 0.9965 (same files) and its half-step check sent those
# designs to a quarter of the step (benchmarks/bench_order4_check.py)
CONTACT_ORDER = 4
# ... and its step check solves the same start at COARSE x the step, not half of it (0.7 x the
# cost of the solve it judges, where half the step costs 2 x), taking the change as of order
# COARSE_CHECK_ORDER: at 1.5 x the step (dt x omega_max = 1.8, the composition's stability
# limit being 2.72) the error still grew 4.0-4.8 x where 1.5^4 = 5.1, so an estimate taken
# as fourth order fell to 0.74 x the true error, and one taken as third order was 1.25-1.6 x it
# (same file). A fourth-order solve that this check rejects, or whose coarser solve failed, is
# re-solved once at half its step where that is predicted to pass, judged by the pair (its
# change from the whole step, as of the same order); else Dopri8
COARSE = 1.5
COARSE_CHECK_ORDER = 3
# ... except where a static pre-compression already closes voids past the cutoff
# (`choose_config`): there the barrier's stiffness at the start is in omega_max, and the fourth
# order takes STATIC_CONTACT_STEP x Verlet's step (dt x omega_max = 1.8, two thirds of its
# stability limit), judged by the same start at Verlet's step (1 / COARSE of its own,
# `check_config`, marked `finer_check`), which stands in its place where the larger step
# does not and its own error by the pair passes. On the focus-vs-protect runs' 8 % designs
# the fourth order at 1.5 x the step was within 2.0e-7 to 2.2e-6 of J with cosines
# 0.9999998-1.0000000 in 0.60-0.81 x the time of the step
# (bench_order4_substeps_8pct_amd.json, bench_order4_substeps_8pct_task_amd.json); the
# reverse pass, which the check does not need, shrinks with it. Where contact is entered under
# the pulse the barrier's stiffness is not in omega_max, and the step stays Verlet's
STATIC_CONTACT_STEP = COARSE
# dt x omega_max the fourth-order composition is stable to (Verlet: 2); the evaluator re-chooses
# a step at STEP_RECHECK of the stability limit of the scheme that takes it (`stability_limit`)
ORDER4_STABILITY = 2.72
# an adaptive solve whose gradient an optimiser takes (`for_gradient`) of a scene whose pulse
# starts in contact (`start_in_contact`: a static pre-compression past the cutoff, a ramp)
# controls its error to this absolute tolerance on mm and mm/s instead of the reference's 1e-4
# (with states of millimetres, rtol 1e-8 is far below either, so atol sets the steps). At
# 1e-4 Dopri8's J on a focus-vs-protect design at 8 % was within 3.4e-6 but its gradient
# pointed 0.99986 along the tight solve's (cosine); at 1e-5 0.9999999 on the three designs
# charted, for about the same time: there the steps are held by the solver's stability, not
# its tolerance
# (`benchmarks/bench_step_convergence.py --adaptive-rtols 1e-8 --adaptive-atols 1e-3 1e-4 1e-5`).
# Where the pulse starts out of contact the reference's 1e-4 stays: on six designs that enter
# contact under the pulse (five of the focus-vs-protect front's 1 % scene, the focusing run's
# evaluation 15) J within 1.1e-6 and cosine 1.0000000 at 1e-4, in 0.72-0.81 x the time of 1e-5
# (bench_step_convergence_atol_*.json, bench_step_convergence_fvp_start30.json)
GRADIENT_ATOL = 1e-5
# ... and its reverse pass recomputes the steps between stored states (diffrax's recursive
# checkpointing). With the default of log(max_steps) states it recomputes each step several
# times; with a state stored per step, once. Dopri8 on two focus-vs-protect designs at 8 %
# (24x18, 1591 and 2626 steps): reverse 9.7 and 16.6 s with the default, 8.1 and 13.4 s with
# one state per step, gradients equal (`benchmarks/bench_reverse_split.py --solver dopri8`);
# each state measured 72-85 bytes per free DOF. So the gradient's solves store as many states
# as GRADIENT_CHECKPOINT_BYTES hold (2928 on 24x18), at most max_steps
CHECKPOINT_BYTES_PER_DOF = 80
GRADIENT_CHECKPOINT_BYTES = 256 * 2**20


@dataclass(frozen=True)
class Choice:
    """A configuration and the reasons it was picked (one line each)."""

    config: SolverConfig
    reasons: tuple[str, ...]
    omega_max: float | None = None  # rad/ms


def make_frequency_estimator(scene: Scene, iterations: int, use_contact: bool = True):
    """Factory: jitted `estimate(x, v0, q_base=None) -> (omega_max, v)` for designs `x`
    [n_design] (mm); `use_contact=False`: of the stiffness without the contact terms (the
    ligaments' alone; `benchmarks/bench_outer_step.py` sets the two side by side).

    Power iteration on M^-1/2 K M^-1/2 with Hessian-vector products (no dense Hessian:
    `iterations` force-gradient products), started from `v0` [n_free] (unit vector), K taken at
    `q_base` ([n_blocks, 3] mm/rad, contact included; default the reference state, at rest).
    Warm-started from the previous eigenvector, a few dozen iterations track omega_max (rad/ms)
    while an optimiser changes the unit masses. The Rayleigh quotient approaches omega_max from
    below.
    """
    lat, free = scene.lattice, scene.supports.free
    energy = make_energy(lat, model=scene.model, use_contact=use_contact)
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


def max_angular_frequency(scene: Scene, iterations: int = 300, state=None,
                          use_contact: bool = True) -> float:
    """Largest omega (rad/ms) of K phi = omega^2 M phi for the scene's design, K taken at
    `state` ([n_blocks, 3] mm/rad; default the reference state at rest), with or without the
    contact terms.

    Power iteration (see `make_frequency_estimator`): a few hundred force evaluations.
    """
    omega, _ = make_frequency_estimator(scene, iterations, use_contact)(
        jnp.asarray(scene.design), jnp.asarray(initial_vector(scene)), state)
    return float(omega)


def choose_config(scene: Scene, *, full_model: bool = False,
                  safety: float = STABILITY_SAFETY, omega: float | None = None,
                  state=None) -> Choice:
    """Pick the configuration for `scene` (see module docstring).

    `omega` (rad/ms) is a measured highest natural frequency of the scene's design at the state
    the pulse starts from (`state` [n_blocks, 3], mm/rad: rest, or for a static pre-compression
    the equilibrium, `run.prestressed_state`); None measures it.
    """
    if full_model:
        return Choice(SolverConfig(), ("forced full model: Dopri5, rtol 1e-8, atol 1e-4, float64, "
                                       "nonlinear strains, contact",))
    ld = scene.loading
    if ld.strain > 0.0 and not ld.is_static:
        return Choice(contact_config(), (
            "dynamic pre-compression ramp (the reference's protocol; tens to hundreds of ms "
            "before the pulse): adaptive Dopri8, rtol 1e-8, atol 1e-4, with contact",))
    where, in_contact = "at rest", False
    if ld.strain > 0.0:
        where = "in the static pre-compression"
        state = static_state(scene) if state is None else state
        margin = static_void_margin(scene, state)
        in_contact = past_cutoff(margin, scene)
    omega = max_angular_frequency(scene, state=state) if omega is None else omega
    dt = fixed_step(omega, FixedStepVerlet(), safety)
    native = scene.model == DEFAULT_MODEL and native_available()
    # remat: the reverse pass recomputes the steps instead of storing their intermediates; on
    # the 24x16 focusing design in contact (6965 steps) value-and-gradient took 13.1-13.4 s
    # CPU against 16.1-16.4 s, and 19 MB of residuals against 2.2 GB
    # (benchmarks/bench_contact_step.py --profile): memory traffic, not arithmetic, was the cost.
    # Since then a step at a time, from its stored start state (`fixed_step.march`); a native
    # step (`physics.native.stages`) is not recomputed whatever this says
    # native_force: the forces by the native custom calls where they can be built (the same
    # force to rounding, a force evaluation 3.7x and its reverse 4-5x faster than XLA's,
    # benchmarks/bench_force_pieces.py -> bench_force_pieces_native_amd.json)
    config = SolverConfig(solver=FixedStepVerlet(max_dt=dt, remat=True), use_contact=False,
                          dtype="float32", native_force=native)
    if in_contact:
        config = with_contact(dataclasses.replace(config, dtype="float64"))
        solver = dataclasses.replace(config.solver, finer_check=True)
        config = dataclasses.replace(config, solver=solver.with_max_dt(
            fixed_step(omega, solver, safety)))
    # reasons[1] is the line about the step (the evaluator replaces it when it re-chooses it)
    reasons = (
        f"highest natural frequency {where} {omega / (2 * np.pi) * 1e3:.0f} Hz",
        step_reason(config.solver.max_dt, config.solver, safety),
        *(() if in_contact else
          ("float32: within 1e-5 of J and 3e-3 of the gradient on the focusing chart",)),
        *(("forces by the native custom calls (physics.native): the same force to rounding, "
           "3-5x faster per evaluation; each step one native call (its Verlet stages)",)
          if native else ()),
        *(() if in_contact else (
            "contact terms left out while every void stays above the contact cutoff (checked "
            "after each solve; exact then, else re-solved with contact by the fourth order at "
            "the same step, judged at a coarser step, else with Dopri8)",)),
        *(("static pre-compression: the pulse starts from rest in the equilibrium under the "
           "closed stages (float64 Newton continuation, implicit gradient)",)
          if ld.strain > 0.0 else ()),
        *((f"the static pre-compression already closes voids past the contact cutoff "
           f"({np.degrees(margin):.2f} deg above the asymptote): contact terms on, by the fourth "
           f"order at {STATIC_CONTACT_STEP:g} x Verlet's step, float64, from the first solve",)
          if in_contact else ()),
    )
    return Choice(config, reasons, omega)


# jitted smallest followed void angle per lattice (`static_void_margin`), keyed by what a
# lattice is built from (as `run.compile_key` keys a topology)
_SMALLEST_VOIDS: dict[tuple, object] = {}


def static_void_margin(scene: Scene, state) -> float:
    """Smallest void angle of `state` [n_blocks, 3] (mm, rad) above the contact asymptote, rad.
    One compiled program per lattice (op by op it took 20-45 ms a call; the design loop asks
    for it on every solve of a scene without contact terms)."""
    lat = scene.lattice
    key = (lat.kind, lat.shape, lat.spacing, lat.ligament_length)
    if key not in _SMALLEST_VOIDS:
        def smallest(design, q):
            bonds = bond_geometry(lat, block_geometry(lat, design))
            return jnp.min(followed_voids(bonds.void_ref, q, lat.bond_blocks))

        _SMALLEST_VOIDS[key] = jax.jit(smallest)
    smallest_void = _SMALLEST_VOIDS[key](np.asarray(scene.design, np.float64),
                                         np.asarray(state, np.float64))
    return float(smallest_void) - float(scene.material.contact_min)


def contact_frequency(min_void_margin: float, material, min_inertia: float,
                      model: Model = DEFAULT_MODEL) -> float:
    """Upper bound (rad/ms) of the frequency the contact law adds at its deepest point.

    At the deepest void angle alpha (`min_void_margin` rad above the asymptote, as
    `Solution.min_void_margin` gives it; taken just inside the cutoff and short of the
    asymptote) the model's stiffness in that angle, d2V/dalpha2 (N mm/rad, differentiated from
    the law itself: `energy.void_stiffness`; for the default barrier
    k_c (1 + 3 tau^2) / (1 - tau^2)^3), joins two units of rotary inertia >= `min_inertia`
    (g mm^2): they vibrate at most at sqrt(2 d2V/dalpha2 / min_inertia).
    """
    span = float(material.contact_cutoff - material.contact_min)
    tau = min(max((span - float(min_void_margin)) / span, 1e-9), 1.0 - 1e-12)
    alpha = float(material.contact_cutoff) - tau * span
    stiffness = void_stiffness(model, material, alpha)
    return float(np.sqrt(2.0 * max(stiffness, 0.0) / min_inertia))


def contact_config() -> SolverConfig:
    """Configuration for scenes in contact: Dopri8 at the reference tolerances, with contact,
    its right-hand side by the native force where it can be built (`SolverConfig.native_force`;
    the judge of the charts, `SolverConfig()`'s Dopri5 and the re-checks' Dopri8, keep JAX's)."""
    return SolverConfig(solver=diffrax.Dopri8(), native_force=native_available())


def for_gradient(config: SolverConfig, scene: Scene) -> SolverConfig:
    """`config` as an optimiser's value and gradient solves `scene` (at its own design) with
    it: an adaptive one, where the pulse starts in contact (`start_in_contact`), with atol at
    most GRADIENT_ATOL, and, unless its adjoint was chosen, as many checkpoints as
    GRADIENT_CHECKPOINT_BYTES hold for the scene's free DOFs (at most its max_steps); a fixed
    step as it is. Raises `SimulationError` when a static pre-compression's equilibrium is not
    found."""
    if is_fixed_step(config.solver):
        return config
    if config.adjoint == SolverConfig().adjoint:
        n_free = max(int(scene.supports.free.size), 1)
        states = GRADIENT_CHECKPOINT_BYTES // (CHECKPOINT_BYTES_PER_DOF * n_free)
        config = dataclasses.replace(config, adjoint=diffrax.RecursiveCheckpointAdjoint(
            checkpoints=int(max(1, min(config.max_steps, states)))))
    if config.atol <= GRADIENT_ATOL or not start_in_contact(scene):
        return config
    return dataclasses.replace(config, atol=GRADIENT_ATOL)


def start_in_contact(scene: Scene) -> bool:
    """Whether the state the scene's pulse starts from, at its own design, has a void past the
    contact cutoff: the equilibrium of a static pre-compression (`simulate.static_state`, kept once
    solved), or rest; a dynamic ramp's start counts as in contact (its stages close the voids
    before the pulse). Raises `SimulationError` when the equilibrium is not found."""
    ld = scene.loading
    if ld.strain > 0.0 and not ld.is_static:
        return True
    state = static_state(scene) if ld.strain > 0.0 else np.zeros((scene.n_units, 3))
    return past_cutoff(static_void_margin(scene, state), scene)


def past_cutoff(void_margin: float, scene: Scene) -> bool:
    """Whether a void `void_margin` rad above the contact asymptote is past the contact cutoff,
    where the contact law acts."""
    return float(void_margin) < float(scene.material.contact_cutoff - scene.material.contact_min)


def needs_contact(config: SolverConfig, min_void_margin: float, scene: Scene) -> bool:
    """True if a solve without contact let a void angle reach the contact cutoff (so its result
    differs from the full model's and must be recomputed with contact)."""
    return (not config.use_contact) and past_cutoff(min_void_margin, scene)


def with_contact(config: SolverConfig) -> SolverConfig:
    """Configuration for a scene whose voids reached the contact cutoff: the same fixed step, in
    the same precision, by the fourth-order composition of Verlet steps (CONTACT_ORDER), with
    the contact terms and the contact substeps it had (at least CONTACT_ENTRY_SUBSTEPS), or
    Dopri8 for an adaptive solve.

    The precision is kept: float32 for contact entered under the pulse (the default choice),
    float64 for a static pre-compression already in contact (`choose_config`). On the energy
    chart (`benchmarks/bench_energy_check.py`) float32 with contact is as accurate as float64
    where the step is right (the optimised 24x16 focusing design: 1.4e-5 of J; 12x10 at 5 and
    8 %: 5.1e-5 and 1.4e-4 against float64's 6.8e-5 and 1.2e-4) and its wrong solves drift as
    far past the tolerance (8x6 at 44 deg under 4 and 6 mm pulses: 3.1e-3 and 2.2e-3, J off by
    37 % and 53 %), so the work-energy check rejects them in either precision; with the fourth
    order, float32 changed J by up to 1.5e-5 and the gradient's cosine by 1e-7
    (bench_order4_substeps_*_amd.json)."""
    if is_fixed_step(config.solver) and config.solver.stability_limited:
        config = dataclasses.replace(config, use_contact=True)
        if hasattr(config.solver, "contact_substeps"):
            config = dataclasses.replace(config, solver=dataclasses.replace(
                config.solver, order=CONTACT_ORDER,
                contact_substeps=max(config.solver.contact_substeps, CONTACT_ENTRY_SUBSTEPS)))
        return config
    return contact_config()


def needs_step_check(config: SolverConfig, health: dict, scene: Scene) -> bool:
    """Whether an accepted fixed-step solve is also to be judged at half its step
    (STEP_ERROR_TOLERANCE): one with contact whose voids reached the contact cutoff, at its
    start (a static pre-compression past it) or under the pulse (`void_margin`, the deepest
    over every sample, the first included). A solve with contact whose voids stayed clear of
    the cutoff solved the model without contact terms, which the work-energy balance bounds."""
    return (config.use_contact and is_fixed_step(config.solver)
            and config.solver.stability_limited
            and past_cutoff(health.get("void_margin", np.inf), scene))


def contact_step_ratio(solver, health: dict, scene: Scene) -> float:
    """h x omega_c of a fixed-step solve with contact: the step its contact forces take (the
    step over its substeps) times the barrier's frequency at the deepest void of `health`."""
    return (solver.max_dt / getattr(solver, "contact_substeps", 1)
            * contact_frequency(float(health["void_margin"]), scene.material,
                                float(health["min_inertia"]), scene.model))


def barrier_ratio(config: SolverConfig, health: dict, scene: Scene) -> float:
    """The h x omega_c that `next_config` holds to CONTACT_STEP_LIMIT: Verlet's with contact
    (`contact_step_ratio`); 0 for the fourth order, which its step check judges instead. There
    the bound on omega_c came out at 1.4-4.2 / h with one contact substep (the stage's own
    step 0.66 h) on solves within 4.3e-9 to 1.5e-5 of J, where substepping the contact
    forces to bring it within 1 made J worse, 1.4e-5 to 7.6e-5 off, in 1.5-2.2 x the time
    (bench_order4_substeps_{8pct,focusing}_amd.json): a bound, not the barrier's frequency,
    and the composition is stable to dt x omega_max = 2.72 with the barrier in omega_max."""
    if not (config.use_contact and is_fixed_step(config.solver)) or order_of(config.solver) != 2:
        return 0.0
    return contact_step_ratio(config.solver, health, scene)


def relative_step_error(value: float, other: float, ratio: float = REFINE,
                        order: int = 2) -> float:
    """The relative error of a fixed-step objective `value` estimated from the same start solved
    at `ratio` x the step (`other`), the error taken as growing with the step to the power
    `order` (Richardson): by default half the step and Verlet's second order, 4/3 of the change
    (`policy.STEP_ERROR_TOLERANCE`); inf when the other value is not finite."""
    if not np.isfinite(other):
        return float("inf")
    return abs(value - other) / abs(ratio**order - 1.0) / max(abs(value), 1e-300)


def order_of(solver) -> int:
    """The order of a fixed step's scheme (2: Verlet; 4: `FixedStepVerlet(order=4)`)."""
    return getattr(solver, "order", 2)


def verlet_multiple(solver) -> float:
    """A fixed step's multiple of Verlet's step at the same omega_max: STATIC_CONTACT_STEP
    where marked `finer_check` (`choose_config`), else 1."""
    return STATIC_CONTACT_STEP if getattr(solver, "finer_check", False) else 1.0


def fixed_step(omega: float, solver, safety: float = STABILITY_SAFETY) -> float:
    """The fixed step (ms) `solver`'s kind takes at highest natural frequency `omega` (rad/ms):
    `safety` x Verlet's stability limit 2 / omega, x `verlet_multiple` (`choose_config`; the
    evaluator's re-chosen step, `TaskEvaluator._check_step`)."""
    return safety * verlet_multiple(solver) * 2.0 / omega


def step_reason(dt: float, solver, safety: float = STABILITY_SAFETY,
                current: bool = False) -> str:
    """The reasons' line about fixed step `dt` (ms) of `solver`'s kind (`choose_config`'s
    second; the evaluator's after it re-chose the step, `current`: of the current design)."""
    limit = "Verlet's stability limit" + (" of the current design" if current else "")
    multiple = verlet_multiple(solver)
    if multiple > 1.0:
        return (f"the fourth order, dt = {dt * 1e3:.1f} us = {multiple:g} x {safety:g} x {limit} "
                f"(5 force evaluations per step; judged at Verlet's step, "
                f"{dt / multiple * 1e3:.1f} us)")
    return (f"fixed-step Verlet, dt = {dt * 1e3:.1f} us = {safety:g} x {limit} (1 force "
            "evaluation per step; within 0.5 % of J and 1 % of the gradient on the focusing chart)")


def stability_limit(omega: float, solver) -> float:
    """The largest stable step (ms) at `omega` (rad/ms) of the scheme `solver` takes its step
    by: Verlet's 2 / omega; ORDER4_STABILITY / omega where the fourth order takes a multiple
    of Verlet's step (`verlet_multiple`), whose margin is then its own. The evaluator
    re-chooses a step above STEP_RECHECK of it: at 1.2 x Verlet's limit (0.88 of its own) a
    1.5 x step had drifted to 1.3 x on a seeded focus-vs-protect run, dt x omega_max = 2.6,
    and diverged (bench_fvp_run_session_seed1_amd.json, evaluation 18)."""
    return (ORDER4_STABILITY if verlet_multiple(solver) > 1.0 else 2.0) / omega


def check_ratio(config: SolverConfig) -> float:
    """The step of a fourth-order solve's check over its own (`check_config`): COARSE, or
    1 / COARSE where its step is above Verlet's (`verlet_multiple`, the mark `finer_check`)."""
    return 1.0 / COARSE if verlet_multiple(config.solver) > 1.0 else COARSE


def check_config(config: SolverConfig) -> SolverConfig:
    """The configuration the step check solves a fixed-step solve's start with
    (`needs_step_check`): half the step (`refined`) for Verlet, `check_ratio` x the step for
    the fourth order (COARSE, or 1 / COARSE where marked `finer_check`; then marked refined,
    so that where it stands in place of the step it judges, the next evaluations climb back)."""
    if order_of(config.solver) == 2:
        return refined(config)
    ratio = check_ratio(config)
    return dataclasses.replace(config, solver=dataclasses.replace(
        config.solver, max_dt=config.solver.max_dt * ratio,
        refined=config.solver.refined or ratio < 1.0))


def coarse_step_error(value: float, other: float, ratio: float = COARSE) -> float:
    """A fourth-order solve's estimate from the same start solved at `ratio` x its step
    (`check_config`, `check_ratio`), taken as of order COARSE_CHECK_ORDER."""
    return relative_step_error(value, other, ratio, COARSE_CHECK_ORDER)


def after_coarse_check(step_error: float, config: SolverConfig) -> bool:
    """After a fourth-order solve with `config` that passed its other checks and whose coarser
    check estimated `step_error` over STEP_ERROR_TOLERANCE (inf where that solve failed):
    whether to solve the same start at half the step (`refined`), to be judged by the pair
    (`half_step_pair_error`). Not for a refined step; not for a step judged at a finer one
    (`finer_check`: that solve is the candidate, `driver`); not where the half is not
    predicted to pass (the estimate x REFINE^COARSE_CHECK_ORDER within half the tolerance; a
    failed check predicts nothing, and the half is tried)."""
    return not (config.solver.refined or check_ratio(config) < 1.0) and (
        not np.isfinite(step_error)
        or step_error_passes(step_error * REFINE**COARSE_CHECK_ORDER))


def half_step_pair_error(half: float, whole: float) -> float:
    """The error of a fourth-order solve at half a step (`half`) by the pair it makes with the
    whole step's (`whole`), taken as of order COARSE_CHECK_ORDER."""
    return relative_step_error(half, whole, 1.0 / REFINE, COARSE_CHECK_ORDER)


DEEPER, HALF, QUARTER, REJECT = "deeper", "half", "quarter", "reject"


def moved(step_error: float, half_error: float | None = None, order: int = 2,
          ratio: float = COARSE) -> str:
    """Why a fixed-step solve's half-step estimate `step_error` rejects it (with `half_error`,
    the half-step solve's own estimate at a quarter of the step, where it was judged so); of
    a fourth-order solve (`order`), its estimate at `ratio` x the step (`check_ratio`; and
    with `half_error`, that of the solve that could stand in its place: the half step's or the
    finer check's, by the pair)."""
    where = "half the step" if order == 2 else f"{ratio:.2g} x the step"
    why = (f"the objective moved by {float(step_error):.2e} of itself at {where} "
           f"(> {STEP_ERROR_TOLERANCE:g}; a solve in contact, where the work-energy "
           "balance does not bound it)")
    if half_error is None:
        return why
    if order != 2:
        which = "finer solve's" if ratio < 1.0 else "half-step solve's"
        return f"{why}, and its {which} error by the pair was {float(half_error):.2e}"
    why = f"{why}, and by {float(half_error):.2e} between a half and a quarter of the step"
    if not float(half_error) > 0.0:
        return why
    return f"{why} (the changes {float(step_error) / float(half_error):.1f}:1)"


def after_half_step(step_error: float, half: SolverConfig, half_health: dict,
                    scene: Scene) -> str:
    """After a fixed-step solve whose objective moved by `step_error` (over
    STEP_ERROR_TOLERANCE, Richardson-scaled) when the same start was solved at half its step
    (`half`, with its `solve_health` `half_health`): DEEPER when the half-step solve is to be
    judged at its own half (its other checks pass, `next_config`, and the quarter of the step
    is predicted to pass: the estimate x REFINE^4 within half the tolerance), so that the
    half or the quarter may stand (`after_quarter_step`), else REJECT (then `next_config`
    says Dopri8)."""
    if (np.isfinite(step_error) and next_config(half, half_health, scene) is None
            and step_error_passes(step_error * REFINE**4)):
        return DEEPER
    return REJECT


def after_quarter_step(step_error: float, half_error: float, half: SolverConfig,
                       quarter: SolverConfig, quarter_health: dict,
                       scene: Scene) -> tuple[str, str]:
    """After `after_half_step` said DEEPER and the same start was solved at a quarter of the
    step (`quarter`, with its `quarter_health`): which solve stands and why. HALF when the
    half-step solve's own estimate (`half_error`, from it and the quarter) is within
    STEP_ERROR_TOLERANCE: judged as the whole step was. QUARTER when the quarter's own error by
    the same pair (`half_error` x REFINE^2) is within it, its other checks pass, and the two
    changes show the step's second order (`step_error` / `half_error` at least
    STEP_CONVERGENCE_MIN, where 4 is second order: a pair whose changes do not shrink, the
    step not yet converging, says nothing of the error). Else REJECT."""
    what = moved(step_error, half_error)
    if half_error <= STEP_ERROR_TOLERANCE:
        return HALF, (f"{what}: the half-step solve ({half.solver.max_dt * 1e3:.1f} us) stands "
                      "on its own estimate")
    own = half_error * REFINE**2
    if (np.isfinite(half_error) and own <= STEP_ERROR_TOLERANCE
            and step_error >= STEP_CONVERGENCE_MIN * half_error
            and next_config(quarter, quarter_health, scene) is None):
        return QUARTER, (f"{what}: the quarter-step solve ({quarter.solver.max_dt * 1e3:.1f} us)"
                         f" stands, its own error by that pair {own:.2e}")
    return REJECT, ""


def step_error_passes(step_error: float) -> bool:
    """Whether a predicted half-step estimate `step_error` passes STEP_ERROR_TOLERANCE with the
    margin a prediction needs (within half of it)."""
    return step_error <= 0.5 * STEP_ERROR_TOLERANCE


def predicted_drift(drift: float, config: SolverConfig, factor: float) -> float:
    """The work-energy drift that a fixed-step solve of `config` which drifted by `drift`
    predicts at another step, whose error is `factor` x its own (REFINE^order refining,
    REFINE^-order climbing back): `factor` x `drift`, or 0 where the drift is within its
    precision's rounding (`DRIFT_FLOOR`), which predicts nothing of another step."""
    return 0.0 if drift <= DRIFT_FLOOR.get(config.dtype, 0.0) else factor * drift


def passes(drift: float, ratio: float) -> bool:
    """Whether a fixed-step solve is predicted to pass `next_config` with this drift and
    h x omega_c, with the margin a prediction needs (the drift within half the tolerance)."""
    return drift <= 0.5 * ENERGY_TOLERANCE and ratio <= CONTACT_STEP_LIMIT


def with_substeps(config: SolverConfig, n: int) -> SolverConfig:
    """The same fixed-step configuration with its contact forces stepped `n` times a step."""
    return dataclasses.replace(config, solver=dataclasses.replace(config.solver,
                                                                  contact_substeps=n))


def next_config(config: SolverConfig, health: dict, scene: Scene) -> tuple[SolverConfig, str] | None:
    """After a solve that did not fail (`simulate.solve_health` scalars): the configuration to
    solve again with and why, or None when the result stands.

    - voids reached the contact cutoff without contact terms: `with_contact(config)`;
    - a `step_error` in `health` (the driver's half-step check, `needs_step_check`) above
      STEP_ERROR_TOLERANCE: Dopri8 (the driver has already tried the half-step solves,
      `after_half_step`, or for the fourth order `after_coarse_check`);
    - an explicit fixed-step solve whose work-energy balance drifted by more than
      ENERGY_TOLERANCE of the energy it moved (`Solution.energy_error`), or, with contact, whose
      barrier frequency at the deepest void (`contact_frequency`) exceeds CONTACT_STEP_LIMIT /
      the contact forces' step: when the drift is within the tolerance, re-solved at the same
      step with the contact forces substepped (`CONTACT_SUBSTEPS_MAX`); else re-solved once at
      REFINE x the step (`refined`) when that is predicted to pass (the drift to half the
      tolerance), else (and for a refined step rejected again) with Dopri8 (`contact_config`).
    """
    margin = float(health["void_margin"])
    if needs_contact(config, margin, scene):
        nxt = with_contact(config)
        how = ("the fourth order at the same step" if is_fixed_step(nxt.solver)
               else "adaptive Dopri8")
        return nxt, f"a void reached the contact cutoff: re-solved with contact ({how})"
    solver = config.solver
    if not (is_fixed_step(solver) and solver.stability_limited):
        return None
    step_error = health.get("step_error")
    if step_error is not None and not float(step_error) <= STEP_ERROR_TOLERANCE:
        why = moved(step_error, health.get("half_step_error"), order_of(solver),
                    check_ratio(config))
        return contact_config(), f"{why}: re-solved with adaptive Dopri8"
    drift = float(health.get("energy_error", 0.0))
    substeps = getattr(solver, "contact_substeps", 1)
    ratio = barrier_ratio(config, health, scene)
    faults = []
    if not drift <= ENERGY_TOLERANCE:
        faults.append(f"the work-energy balance drifted by {drift:.1e} of the energy the solve "
                      f"moved (> {ENERGY_TOLERANCE:g})")
    if ratio > CONTACT_STEP_LIMIT:
        faults.append(f"the contact barrier stiffened past the step (dt x omega_c = {ratio:.2f} "
                      f"> {CONTACT_STEP_LIMIT:g})")
    if not faults:
        return None
    what = "; ".join(faults)
    if drift <= ENERGY_TOLERANCE and hasattr(solver, "contact_substeps"):
        n = substeps * 2
        while n * CONTACT_STEP_LIMIT < ratio * substeps and n < CONTACT_SUBSTEPS_MAX:
            n *= 2
        if ratio * substeps <= n * CONTACT_STEP_LIMIT:
            nxt = with_substeps(config, n)
            return nxt, (f"{what}: re-solved with the contact forces stepped {n} times per step "
                         f"({nxt.solver.max_dt / n * 1e3:.1f} us)")
    if not solver.refined and passes(predicted_drift(drift, config, REFINE**order_of(solver)),
                                     ratio * REFINE):
        nxt = refined(config)
        return nxt, (f"{what}: re-solved once at {REFINE:g} x the step "
                     f"({nxt.solver.max_dt * 1e3:.1f} us)")
    return contact_config(), f"{what}: re-solved with adaptive Dopri8"


def after_failure(config: SolverConfig) -> tuple[SolverConfig, str] | None:
    """After a fixed-step solve with contact that failed (diverged, went non-finite or through
    the barrier, most likely the barrier outgrowing its step): for Verlet, the same step with
    the contact forces substepped CONTACT_SUBSTEPS_MAX times (a substepped solve costs about a
    tenth of Dopri8's); for the fourth order, whose contact forces go with the rest, the same
    start once at REFINE x the step (`refined`), which an optimiser's next evaluations climb
    back from (`start_config`). Substeps there stayed for the rest of a focus-vs-protect run:
    its 8 % evaluations took 13-29 s with 8 of them against 10-13 s before
    (bench_fvp_run_order4_all_amd.json), where they also cost accuracy
    (bench_order4_substeps_8pct_amd.json). And why; None when the step was refined, or
    substepped as much, already (then `fallback_config`)."""
    solver = config.solver
    if not (config.use_contact and is_fixed_step(solver) and solver.stability_limited):
        return None
    if order_of(solver) != 2:
        if solver.refined:
            return None
        nxt = refined(config)
        return nxt, f"re-solved once at {REFINE:g} x the step ({nxt.solver.max_dt * 1e3:.1f} us)"
    if getattr(solver, "contact_substeps", CONTACT_SUBSTEPS_MAX) >= CONTACT_SUBSTEPS_MAX:
        return None
    n = CONTACT_SUBSTEPS_MAX
    nxt = with_substeps(config, n)
    return nxt, (f"re-solved with the contact forces stepped {n} times per step "
                 f"({solver.max_dt / n * 1e3:.1f} us)")


def refined(config: SolverConfig) -> SolverConfig:
    """The same fixed-step configuration at REFINE x its step, marked refined."""
    solver = dataclasses.replace(config.solver, max_dt=config.solver.max_dt * REFINE, refined=True)
    return dataclasses.replace(config, solver=solver)


def start_config(choice: SolverConfig, last: SolverConfig | None, health: dict | None,
                 scene: Scene) -> SolverConfig:
    """The configuration an optimiser's next evaluation starts with: the one the previous
    evaluation ended with (`last`, with its `solve_health`) while its voids still reached the
    contact cutoff, since the next design, a small step away, most likely needs it too (it
    saves the no-contact solve that `next_config` would reject); a fixed step with contact also
    after the voids left the cutoff (it solves the full model, and a run that went back and
    forth compiled a program for each at every new step); else the choice. When the
    previous evaluation ended with Dopri8 after a rejected fixed step, the fixed step with
    contact gets its chance again (`with_contact(choice)`): it costs 1/15-1/25 of Dopri8 and a
    design a step away may be accepted at it. A refined step (`refined`) climbs back one
    halving an evaluation toward the choice's step (marked refined while below it), unless the
    last solve predicts that step would be rejected again by the work-energy balance (its drift
    x 1 / REFINE^order above half the tolerance; a drift within its precision's rounding,
    `DRIFT_FLOOR`, predicts nothing) or, for Verlet, the barrier (past the larger
    step, `barrier_ratio`). Its step estimate is not such a prediction: a failed climb costs one
    forward solve at the larger step, where a step that never climbed would stay halved for the
    rest of the run. Either way
    `next_config` and the step check still judge the result, so this changes the cost, not the
    answer."""
    if last is None or health is None or last == choice or not last.use_contact:
        return choice
    if not past_cutoff(health["void_margin"], scene) and not is_fixed_step(last.solver):
        return choice
    if is_fixed_step(choice.solver) and not is_fixed_step(last.solver):
        return with_contact(choice)
    if is_fixed_step(last.solver) and getattr(last.solver, "refined", False):
        top = (choice.solver.max_dt if is_fixed_step(choice.solver)
               else last.solver.max_dt / REFINE)
        dt = min(last.solver.max_dt / REFINE, top)
        up = dataclasses.replace(last, solver=dataclasses.replace(last.solver, max_dt=dt,
                                                                  refined=dt < top))
        drift = predicted_drift(float(health.get("energy_error", 0.0)), last,
                                REFINE**-order_of(last.solver))
        if passes(drift, barrier_ratio(up, health, scene)):
            return up
    return last


def fallback_config() -> tuple[SolverConfig, str]:
    """The configuration used when a fixed-step solve fails, and why."""
    return contact_config(), ("the fixed-step solve failed (contact stiffening or instability): "
                              "fell back to adaptive Dopri8 at the reference tolerances")
