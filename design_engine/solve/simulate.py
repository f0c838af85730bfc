"""Time integration (the one owner of diffrax): design + load -> sampled trajectory.

`make_simulator(lattice, supports, config)` returns a pure, jittable and differentiable
`simulate(x, material, loading, ts)`; solver failures are returned as a status code alongside the
solution (so value-and-gradient can run under jit) and turned into `SimulationError` by
`check_solution`, never into silent NaNs.
"""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from design_engine._types import Array, DesignVector, Float, Int
from design_engine.physics.dynamics import (VELOCITY_SCALE, make_dynamics_args, make_full_state,
                                            make_rhs)
from design_engine.physics.energy import (DEFAULT_MODEL, Force, Model, followed_voids, jax_force,
                                          make_contact_energy, make_energy)
from design_engine.physics.geometry import block_geometry
from design_engine.physics.lattice import Lattice
from design_engine.physics.loading import Loading, Supports, make_prescribed
from design_engine.physics.material import Material
from design_engine.physics.native.build import available as native_available
from design_engine.physics.native.force import (make_contact_energy_and_gradient,
                                                make_energy_and_gradient)
from design_engine.physics.native.stages import make_verlet_stages
from design_engine.physics.statics import (EquilibriumError, check_equilibrium, equilibrium_state,
                                           make_static_solver)
from design_engine.solve.fixed_step import AbstractFixedStep, is_fixed_step, step_grid


class SolverConfig(eqx.Module):
    """Integrator settings.

    Attributes:
        solver: a diffrax solver object (default Dormand-Prince 5(4), as the reference), or a
            fixed-step scheme (an `AbstractFixedStep`: `FixedStepVerlet`, one force evaluation
            per step; `ImplicitNewmark`, implicit; both need the time grid up front).
        rtol, atol: tolerances on the state (positions mm, velocities mm/s; spec 6.5).
        max_steps: step budget; exceeding it is reported as an error.
        adjoint: gradient method (default: discretise-then-optimise with recursive checkpointing).
        dt0: initial step (ms) or None for the Hairer-Norsett-Wanner heuristic.
        linearized: use the linearised strain measures (spec 5.2).
        use_contact: include the contact barrier (spec 5.3).
        progress: show a tqdm progress bar (forward runs only).
        dtype: floating type of the solve, "float64" (default) or "float32" (inputs are cast;
            outputs come back in that type).
        stretch_scale: factor on the ligament stretch stiffness (model variant): the stiff
            stretch mode sets the explicit step limit while a pulse barely excites it, so a
            softer stretch allows larger steps at an error that the work-precision chart shows.
        native_force: take the default model's forces from the native custom calls
            (`physics.native`) where they can be built, else from JAX: the same forces to
            rounding, for the fixed step (its force and a split step's contact force) and an
            adaptive solver's right-hand side. Reverse-mode derivatives only: a solve with
            `diffrax.ForwardMode` keeps the JAX force, and `jax.jvp` / `jax.jacfwd` of any
            other such solve raises.
    """

    solver: diffrax.AbstractSolver | AbstractFixedStep = diffrax.Dopri5()
    rtol: float = eqx.field(static=True, default=1e-8)
    atol: float = eqx.field(static=True, default=1e-4)
    max_steps: int = eqx.field(static=True, default=200_000)
    adjoint: diffrax.AbstractAdjoint = diffrax.RecursiveCheckpointAdjoint()
    dt0: float | None = eqx.field(static=True, default=None)
    linearized: bool = eqx.field(static=True, default=False)
    use_contact: bool = eqx.field(static=True, default=True)
    progress: bool = eqx.field(static=True, default=False)
    dtype: str = eqx.field(static=True, default="float64")
    stretch_scale: float = eqx.field(static=True, default=1.0)
    native_force: bool = eqx.field(static=True, default=False)


class Solution(eqx.Module):
    """Sampled solution in internal units.

    Attributes:
        ts: [n_t] sample times, ms.
        q: [n_t, n_blocks, 3] (u mm, v mm, theta rad) of every block, prescribed DOFs included.
        qdot: [n_t, n_blocks, 3] rates (mm/ms = m/s, rad/ms).
        mass: [n_blocks] block masses, g.
        inertia: [n_blocks] rotary inertias, g mm^2.
        centroids: [n_blocks, 2] reference area centroids, mm.
        result: diffrax result code (0 = success).
        num_steps, num_accepted, num_rejected: solver statistics.
        min_void_margin: smallest unwrapped void angle minus the contact asymptote over the samples,
            rad; negative means a unit passed through the contact barrier (a failed step).
        start_void_margin: the same at the first sample (for a static scene, the static
            pre-compression's as the pulse has not arrived yet), rad.
        start_free: [n_free] the free DOFs the solve started from at t = 0 (the static
            equilibrium of a static scene, else zeros or the given initial state), mm / rad.
        static_residual: max |dE/dq_f| of the static pre-compression the solve started from
            (N, N mm; 0 without one); above `statics` tolerance the start was no equilibrium.
        energy_error: a fixed-step solve's work-energy drift relative to the energy it moved
            (`fixed_step.energy_error`; 0 for an adaptive solve, whose controller bounds its
            own error).
    """

    ts: Float[Array, " n_t"]
    q: Float[Array, "n_t n_blocks 3"]
    qdot: Float[Array, "n_t n_blocks 3"]
    mass: Float[Array, " n_blocks"]
    inertia: Float[Array, " n_blocks"]
    centroids: Float[Array, "n_blocks 2"]
    result: Int[Array, ""]
    num_steps: Int[Array, ""]
    num_accepted: Int[Array, ""]
    num_rejected: Int[Array, ""]
    min_void_margin: Float[Array, ""]
    start_void_margin: Float[Array, ""]
    start_free: Float[Array, " n_free"]
    static_residual: Float[Array, ""]
    energy_error: Float[Array, ""]


# result code of a fixed-step solve reported not converged (diffrax's meaning)
NOT_CONVERGED = int(diffrax.RESULTS.nonlinear_max_steps_reached._value)
MAX_STEPS_REACHED = int(diffrax.RESULTS.max_steps_reached._value)


class SimulationError(RuntimeError):
    """The solver failed (step budget, non-finite state); the message names the cause."""


class StepBudgetError(SimulationError):
    """The solve used its whole step budget (`SolverConfig.max_steps`) before the window ended."""


def make_simulator(lattice: Lattice, supports: Supports, config: SolverConfig = SolverConfig(),
                   time_grid: np.ndarray | None = None, model: Model = DEFAULT_MODEL):
    """Factory: `simulate(x, material, loading, ts, initial=None, equilibrium=None) -> Solution` (pure;
    jit/grad/vmap).

    Args:
        lattice, supports, config: static set-up.
        time_grid: [n_t] the sample times (ms) the fixed-step solver will be called with; it fixes
            the (static) number of steps. Not needed by the adaptive solvers.

    Args of the returned function:
        x: [n_design] design vector, mm.
        material: `Material`.
        loading: `Loading`.
        ts: [n_t] increasing sample times, ms; the solve runs from t = 0.
        initial: optional (q_f, qdot_f) free-DOF state at t = 0 (default: rest, in the reference
            state, or for a static pre-compression (`loading.is_static`) in the equilibrium
            under the closed stages, solved in float64 with the model's energy and
            differentiated by the implicit function theorem, `statics.make_static_solver`).
        equilibrium: optional [n_free] that equilibrium of this very design, already solved (mm /
            rad, not differentiated): taken as the static start (`make_static_solver`'s
            `start`: no Newton step or load continuation in this program; its residual is
            checked like a solved one's) and differentiated by the implicit function theorem.
            A caller that needs the equilibrium before the solve (the design loop's step check,
            the policy's frequency check) solves it once (`run.static_equilibrium`).
    """
    # a fixed step that steps the contact terms apart (`FixedStepVerlet.contact_substeps`): the
    # slow force without them, the fast one of them alone (from the rotations)
    split = (config.use_contact and is_fixed_step(config.solver)
             and getattr(config.solver, "splits_contact", False))
    energy_fn = make_energy(lattice, linearized=config.linearized,
                            use_contact=config.use_contact and not split, model=model)
    energy_and_gradient = model_force(lattice, config, model, energy_fn, split)
    rhs = make_rhs(supports, energy_and_gradient, VELOCITY_SCALE)
    full = make_full_state(supports)
    _, prescribed = make_prescribed(supports)
    free = np.asarray(supports.free)
    constrained = np.asarray(supports.constrained)
    n_free, nb = free.size, lattice.n_blocks
    free_rotations = np.flatnonzero(free % 3 == 2)  # where the free rotations sit in q_f
    fixed_theta = np.flatnonzero(constrained % 3 == 2)  # where the prescribed ones sit in q_c
    # unit k's rotation is entry theta_order[k] of [free rotations, prescribed rotations]
    theta_order = np.argsort(np.concatenate([free[free_rotations], constrained[fixed_theta]]))
    # the contact energy and its gradient of the rotations in the order the fast force holds them
    contact_fn = fast_contact_force(lattice, config, model, theta_order) if split else None
    bb = np.asarray(lattice.bond_blocks)
    fixed = is_fixed_step(config.solver)
    # a fixed step's Verlet stages in one native call each, where the native force runs it
    stages = (make_verlet_stages(lattice, supports, use_contact=config.use_contact)
              if fixed and not split and _native(config, model) else None)
    if fixed:
        if time_grid is None:
            raise ValueError("the fixed-step solver needs the time grid (time_grid=) up front")
        grid = step_grid(time_grid, config.solver.max_dt)
        integrate = config.solver.make_integrator(grid, bb, free, 3 * nb)
    else:
        term = diffrax.ODETerm(rhs)
        controller = diffrax.PIDController(rtol=config.rtol, atol=config.atol)
        meter = diffrax.TqdmProgressMeter() if config.progress else diffrax.NoProgressMeter()

    def solve_adaptive(args, y0, ts):
        packed = energy_and_gradient.pack(args.bonds, args.material, ts.dtype)
        sol = diffrax.diffeqsolve(
            term, config.solver, t0=jnp.zeros((), ts.dtype), t1=ts[-1], dt0=config.dt0, y0=y0,
            args=(args, packed), saveat=diffrax.SaveAt(ts=ts), stepsize_controller=controller,
            adjoint=config.adjoint, max_steps=config.max_steps, throw=False, progress_meter=meter,
        )
        ys = sol.ys
        stats = (jnp.asarray(sol.result._value, jnp.int32), sol.stats["num_steps"],
                 sol.stats["num_accepted_steps"], sol.stats["num_rejected_steps"])
        return ys[:, :n_free], ys[:, n_free:] / VELOCITY_SCALE, stats, jnp.zeros((), ys.dtype)

    def solve_fixed(args, y0, ts):
        # what the forces read of the design and the material, prepared once, outside the steps
        packed = energy_and_gradient.pack(args.bonds, args.material, ts.dtype)
        fast_packed = contact_fn.pack(args.bonds, args.material, ts.dtype) if split else None

        def force(qf, t):
            # one pass gives the force on the free units, the energy and, from the reactions
            # of the prescribed units, the power their motion puts in (the ledger's inputs)
            potential, grad = energy_and_gradient.evaluate(full(qf, t, args.loading), packed)
            grad = grad.reshape(-1)
            power = jnp.dot(grad[constrained], prescribed(t, args.loading)[1])
            return -grad[free], (potential, power)

        def fast_force(theta_f, t):
            # the contact terms on the free rotations alone; the prescribed rotations' reactions
            # give the power their motion puts in
            qc, qc_dot = prescribed(t, args.loading)

            potential, g = contact_fn.evaluate(jnp.concatenate([theta_f, qc[fixed_theta]]),
                                               fast_packed)
            g_f, g_c = g[:free_rotations.size], g[free_rotations.size:]
            return -g_f, (potential, jnp.dot(g_c, qc_dot[fixed_theta]))

        def native_stages(q, v, f, ledger, t_ends, h):
            qc, qcd = jax.vmap(lambda t: prescribed(t, args.loading))(t_ends)
            return stages(q, v, f, ledger, packed, args.inv_mass, args.damping, qc, qcd, h)

        q0, v0 = y0[:n_free], y0[n_free:] / VELOCITY_SCALE
        n = jnp.asarray(grid.n_steps)
        fast = ({"fast_force": fast_force, "fast_index": free_rotations} if split else
                {"stages": native_stages} if stages is not None else {})
        qs, vs, converged, drift = integrate(force, args.inv_mass, args.damping,
                                             (q0, v0), ts, **fast)
        result = jnp.where(converged, 0, NOT_CONVERGED).astype(jnp.int32)
        return qs, vs, (result, n, n, jnp.asarray(0)), drift

    dtype = jnp.dtype(config.dtype)

    def cast(tree, to=dtype):
        """Floating leaves of `tree` as `to`; the rest unchanged."""
        def leaf(a):
            if isinstance(a, float) or (hasattr(a, "dtype") and jnp.issubdtype(a.dtype, jnp.floating)):
                return jnp.asarray(a, to)
            return a

        return jax.tree_util.tree_map(leaf, tree)

    static_solvers = []  # built on the first static pre-compression (a Hessian colouring)

    def static_start(x, material, loading, equilibrium=None):
        if not static_solvers:
            static_solvers.append(make_static_solver(lattice, supports,
                                                     use_contact=config.use_contact,
                                                     linearized=config.linearized, model=model))
        q_f, info = static_solvers[0](*cast((x, material, loading), jnp.float64), 0.0,
                                      start=equilibrium)
        return (q_f, jnp.zeros_like(q_f)), info["gradient_norm"]

    def simulate(x: DesignVector, material: Material, loading: Loading, ts, initial=None,
                 equilibrium=None) -> Solution:
        if config.stretch_scale != 1.0:
            material = eqx.tree_at(lambda m: m.k_stretch, material,
                                   material.k_stretch * config.stretch_scale)
        residual = jnp.zeros(())
        if initial is None and loading.is_static:
            initial, residual = static_start(x, material, loading, equilibrium)
        x, material, loading, ts, initial = cast((x, material, loading, ts, initial))
        geom = block_geometry(lattice, x)
        args = make_dynamics_args(lattice, supports, geom, material, loading)
        if initial is None:  # every task starts at rest in the reference configuration
            y0 = jnp.zeros(2 * n_free, dtype=ts.dtype)
        else:  # (q_f [n_free] mm/rad, qdot_f [n_free] mm/ms, rad/ms)
            y0 = jnp.concatenate([initial[0], VELOCITY_SCALE * initial[1]])
        qf, vf, (result, steps, accepted, rejected), drift = (
            solve_fixed if fixed else solve_adaptive)(args, y0, ts)
        q = jax.vmap(lambda qq, t: full(qq, t, loading))(qf, ts)
        qc_dot = jax.vmap(lambda t: prescribed(t, loading)[1])(ts)
        v_all = jnp.zeros((ts.shape[0], 3 * nb), vf.dtype)
        v_all = v_all.at[:, free].set(vf).at[:, constrained].set(qc_dot)
        voids = followed_voids(args.bonds.void_ref, q, bb)
        return Solution(
            ts=ts,
            q=q,
            qdot=v_all.reshape(ts.shape[0], nb, 3),
            mass=material.density * geom.areas,
            inertia=material.density * geom.polar_moments,
            centroids=geom.centroids,
            result=result,
            num_steps=steps,
            num_accepted=accepted,
            num_rejected=rejected,
            min_void_margin=jax.lax.stop_gradient(jnp.min(voids) - material.contact_min),
            start_void_margin=jax.lax.stop_gradient(jnp.min(voids[0]) - material.contact_min),
            start_free=jax.lax.stop_gradient(y0[:n_free]),
            static_residual=jax.lax.stop_gradient(residual),
            energy_error=jax.lax.stop_gradient(drift),
        )

    return simulate


def _native(config: SolverConfig, model: Model) -> bool:
    """Whether a solve takes its forces from the native custom calls: where its configuration
    asks for them (`SolverConfig.native_force`), its derivatives are reverse-mode (not
    `diffrax.ForwardMode`), the model is the default nonlinear one and they can be built here
    (`physics.native`)."""
    return (config.native_force and not isinstance(config.adjoint, diffrax.ForwardMode)
            and model == DEFAULT_MODEL and not config.linearized and native_available())


def model_force(lattice: Lattice, config: SolverConfig, model: Model, energy_fn,
                split: bool) -> Force:
    """The `energy.Force` of a solve, `(q [n_blocks, 3], bonds, material) -> (energy, dE/dq)`:
    the native custom call (`_native`), else JAX's gradient of `energy_fn`."""
    if _native(config, model):
        return make_energy_and_gradient(lattice, use_contact=config.use_contact and not split)
    return jax_force(energy_fn)


def fast_contact_force(lattice: Lattice, config: SolverConfig, model: Model, order) -> Force:
    """The `energy.Force` of a split step's fast force, `(theta, bonds, material) -> (contact
    energy, its gradient)`, the rotations held in `order` (`energy.make_contact_energy`): the
    native custom call (`_native`), else JAX's gradient."""
    if _native(config, model):
        return make_contact_energy_and_gradient(lattice, order=order)
    return jax_force(make_contact_energy(lattice, model, order=order))


def solve_health(sol: Solution, xp=jnp) -> dict:
    """Scalars that judge a solve (`health_failure`), cheap to return from a jitted or vmapped
    call: result code, steps, whether the state stayed finite, the largest displacement (mm) and
    rotation (rad), the void margin over the solve and at its start (rad), the static start's
    residual (N, N mm), the smallest rotary inertia (g mm^2) and the fixed step's work-energy
    drift (relative). `xp=np` computes
    them on the host for a solution already out of a jitted call (no op-by-op dispatch)."""
    q, qdot = xp.asarray(sol.q), xp.asarray(sol.qdot)
    return {"result": sol.result, "num_steps": sol.num_steps,
            "finite": xp.all(xp.isfinite(q)) & xp.all(xp.isfinite(qdot)),
            "max_disp": xp.max(xp.abs(q[..., :2])), "max_rot": xp.max(xp.abs(q[..., 2])),
            "void_margin": sol.min_void_margin, "start_void_margin": sol.start_void_margin,
            "static_residual": sol.static_residual,
            "min_inertia": xp.min(xp.asarray(sol.inertia)), "energy_error": sol.energy_error}


def health_failure(health: dict, config: SolverConfig) -> str | None:
    """Why a solve failed, from its `solve_health` scalars (one line), or None if it did not."""
    try:  # a start that is not an equilibrium first: what follows from it is its consequence
        check_equilibrium({"gradient_norm": health["static_residual"]})
        msg = failure_message(int(health["result"]), config)
    except EquilibriumError as exc:
        msg = str(exc)
    if msg is None and not bool(health["finite"]):
        hint = config.solver.unstable_hint() if is_fixed_step(config.solver) else ""
        msg = f"non-finite state during the solve{hint}"
    if msg is None and (float(health["max_disp"]) > 1e4 or float(health["max_rot"]) > 1e2):
        msg = ("the state diverged (displacements above 10 m or rotations above 100 rad): the "
               "step is above the stability limit")
    if msg is None and config.use_contact and float(health["void_margin"]) < 0.0:
        msg = ("a unit passed through the contact barrier (void angle below the asymptote by "
               f"{np.degrees(-float(health['void_margin'])):.2g} deg): the step was too large for "
               "the contact stiffness; use the adaptive solver or a smaller step")
    return msg


def simulation_error(health: dict, config: SolverConfig) -> SimulationError | None:
    """The error a solve with these `solve_health` scalars raises (`health_failure`), or None."""
    msg = health_failure(health, config)
    if msg is None:
        return None
    return (StepBudgetError if int(health["result"]) == MAX_STEPS_REACHED else SimulationError)(msg)


def static_state(scene) -> np.ndarray:
    """[n_blocks, 3] the static pre-compression's equilibrium of `scene`
    (`statics.equilibrium_state`, kept once solved); its failure as the `SimulationError` a
    solve reports (the one translation the policy and `run` share)."""
    try:
        return equilibrium_state(scene)
    except EquilibriumError as exc:
        raise SimulationError(str(exc)) from None


def failure_message(result: int, config: SolverConfig) -> str | None:
    """Human-readable cause of a non-zero diffrax result code, or None for success."""
    if int(result) == 0:
        return None
    if int(result) == MAX_STEPS_REACHED:
        return (f"the solver hit its step budget (max_steps={config.max_steps}); the scene is too "
                "stiff for the explicit solver at this tolerance, or the state blew up")
    if int(result) == NOT_CONVERGED and is_fixed_step(config.solver):
        return config.solver.unconverged_message()
    for name in ("successful", "singular", "breakdown", "divergence", "nonfinite_input",
                 "event_occurred", "discrete_terminating_event_occurred"):
        item = getattr(diffrax.RESULTS, name, None)
        if item is not None and int(item._value) == int(result):
            return f"the solver failed: {name.replace('_', ' ')}"
    return f"the solver failed (diffrax result code {int(result)})"


def check_solution(sol: Solution, config: SolverConfig) -> Solution:
    """Raise `SimulationError` naming the cause if the solve failed (`health_failure`)."""
    err = simulation_error(solve_health(sol, np), config)
    if err is not None and str(err).startswith("non-finite state"):
        bad = ~np.isfinite(np.asarray(sol.q)) | ~np.isfinite(np.asarray(sol.qdot))
        k = int(np.argmax(bad.reshape(bad.shape[0], -1).any(axis=1)))
        err = SimulationError(str(err).replace("during the solve",
                                               f"from t = {float(sol.ts[k]):.4g} ms on"))
    if err is not None:
        raise err
    return sol
