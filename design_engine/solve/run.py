"""High-level runs of a scene: forward simulation with metrics, rig replay, objective + gradient.

This is the API the CLI, the simulated rig and the optimiser use. Inputs and outputs here are
SI where they leave the engine (`Trajectory`, summaries); internal units stay inside.
"""

import dataclasses
import threading
import time
from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from design_engine.physics import units
from design_engine.physics.loading import Loading
from design_engine.physics.regions import row_units
from design_engine.physics.scenes import Scene
from design_engine.solve.driver import solve_with_policy
from design_engine.solve.fixed_step import is_fixed_step, step_grid
from design_engine.solve.objectives import (angular_momentum, block_kinetic_energy, objective_term,
                                            peak_energy_along_units, region_energy,
                                            region_energy_ratio)
from design_engine.solve.policy import Choice, choose_config, for_gradient
from design_engine.solve.simulate import (SimulationError, Solution, SolverConfig, check_solution,
                                          make_simulator, simulation_error, solve_health,
                                          static_state)
from metarig.trajectory import Trajectory

_COMPILED: dict[tuple, object] = {}
_COMPILED_LOCK = threading.RLock()  # solves run on several threads (`design.evaluator`)


def cached_program(key: tuple, build) -> tuple[object, bool]:
    """The programs this process keeps under `key` (`compile_key` plus what else tells them
    apart), built by `build()` the first time: `(programs, built now)`. Building is quick
    (`jax.jit` compiles at the first call), so one lock serves every caller."""
    with _COMPILED_LOCK:
        if key in _COMPILED:
            return _COMPILED[key], False
        _COMPILED[key] = build()
        return _COMPILED[key], True


def compile_key(scene: Scene, config: SolverConfig, tag: str, ts_ms) -> tuple:
    """What tells the programs of a solve of `scene` with `config` at the sample times `ts_ms`
    (ms) apart, under `tag`. A fixed step's programs depend on its step grid
    (`fixed_step.step_grid`), not on the step asked for, nor on the policy's mark of a refined
    one: two steps on one grid (a step re-chosen a few percent from one solved before, a
    refinement equal to a chosen step) share one program, where each traced and lowered one of
    its own (README, "Where a front run's evaluations spend their time")."""
    s = scene.supports
    times = b""
    if is_fixed_step(config.solver):
        times = np.asarray(ts_ms).tobytes()
        config = dataclasses.replace(config, solver=config.solver.on_grid(
            step_grid(ts_ms, config.solver.max_dt)))
    return (tag, scene.lattice.kind, scene.lattice.shape, scene.lattice.spacing,
            scene.lattice.ligament_length, s.constrained.tobytes(), s.channel.tobytes(),
            s.gain.tobytes(), repr(config), times, scene.model)


def compiled_simulator(scene: Scene, config: SolverConfig, ts_ms=None):
    """jit-compiled `simulate(x, material, loading, ts, initial=None)` for this scene's topology
    (cached).

    `ts_ms` (default the scene's sample times) fixes the step count of the fixed-step solver;
    the compiled function must then be called with those sample times.
    """
    ts_ms = scene.sample_times if ts_ms is None else np.asarray(ts_ms)
    return cached_program(compile_key(scene, config, "sim", ts_ms), lambda: jax.jit(
        make_simulator(scene.lattice, scene.supports, config, ts_ms, model=scene.model)))[0]


@dataclass(frozen=True)
class SceneRun:
    """Result of `simulate_scene`.

    Attributes:
        trajectory: SI trajectory on the dynamic window; t starts at 0 at the window start.
        solution: internal-units solution (for further metrics).
        metrics: JSON-ready metrics (SI).
        wall_s: wall time of the solve (compile included on a first call), s.
    """

    trajectory: Trajectory
    solution: Solution
    metrics: dict
    wall_s: float


def to_trajectory(sol: Solution, t0_ms: float = 0.0, ts_ms=None) -> Trajectory:
    """Convert an internal solution to an SI float64 `Trajectory`, time shifted by `t0_ms`.

    `ts_ms` gives the exact requested sample times (the solver may have run in float32).
    """
    ts = np.asarray(sol.ts if ts_ms is None else ts_ms, np.float64)
    q = np.array(sol.q, np.float64)
    q[..., :2] /= units.MM_PER_M
    qdot = np.array(sol.qdot, np.float64)
    qdot[..., 2] *= units.MS_PER_S  # rad/ms -> rad/s; mm/ms == m/s already
    return Trajectory(t=units.time_to_si(ts - t0_ms), q=q, qdot=qdot)


def scene_metrics(scene: Scene, sol: Solution) -> dict:
    """The summary metrics of spec 8 for every target region of the scene (SI)."""
    n_t = scene.n_samples
    ke = np.asarray(block_kinetic_energy(sol))
    total = ke.sum(axis=1)
    out = {
        "t_f_s": units.time_to_si(scene.window),
        "n_samples": n_t,
        "total_ke_mean_J": units.energy_to_si(float(total.mean())),
        "total_ke_max_J": units.energy_to_si(float(total.max())),
        "targets": {},
    }
    for name, ids in scene.targets.items():
        j = float(region_energy(sol, ids))
        out["targets"][name] = {
            "units": [int(b) for b in ids],
            "ke_mean_J": units.energy_to_si(j / n_t),
            "ke_integral_Js": units.energy_to_si(j) * units.time_to_si(scene.window) / (n_t - 1),
            "ratio_to_rest": float(region_energy_ratio(sol, ids)),
        }
        if scene.spin_point is not None:
            lm = float(angular_momentum(sol, ids, scene.spin_point))
            out["targets"][name]["angular_momentum_sum_kgm2_s"] = units.angular_momentum_to_si(lm)
    first = next(iter(scene.targets))
    out["target_blocks"] = out["targets"][first]["units"]
    out["target_ke_mean_J"] = out["targets"][first]["ke_mean_J"]
    line = row_units(scene.lattice, scene.line_row)
    out["line"] = {
        "row": scene.line_row,
        "units": [int(b) for b in line],
        "peak_ke_J": [units.energy_to_si(float(v)) for v in peak_energy_along_units(sol, line)],
    }
    return out


def solver_stats(sol: Solution) -> dict:
    return {"num_steps": int(sol.num_steps), "num_accepted_steps": int(sol.num_accepted),
            "num_rejected_steps": int(sol.num_rejected)}


def static_equilibrium(scene: Scene, config: SolverConfig, x=None):
    """[n_free] the simulator's `equilibrium=` for a solve of design `x` (default the scene's)
    with `config`: the free DOFs of the design's static equilibrium (`prestressed_state`: one
    compiled solver per topology, the last results kept), so that the solve's own program holds no static solver
    (`statics.make_static_solver(start=)`). None where the solve finds its start itself: a
    scene without a static pre-compression, a traced `x`, or a configuration whose static
    energy is not the model's (linearised strains, a scaled stretch stiffness, or contact left
    out where the equilibrium is within the contact cutoff). Raises `SimulationError` when the
    equilibrium is not found."""
    from design_engine.solve.policy import past_cutoff, static_void_margin

    ld = scene.loading
    if (not (ld.strain > 0.0 and ld.is_static) or isinstance(x, jax.core.Tracer)
            or config.linearized or config.stretch_scale != 1.0):
        return None
    if x is not None:
        scene = scene.with_design(np.asarray(x, np.float64))
    state = prestressed_state(scene)
    if not config.use_contact and past_cutoff(static_void_margin(scene, state), scene):
        return None
    return jnp.asarray(state.reshape(-1)[np.asarray(scene.supports.free)])


class StaticStart(NamedTuple):
    """Compiled programs for a solve with `config` that takes the design's static equilibrium
    q_s [n_free] (`static_equilibrium`) as its start state (`initial`) instead of
    differentiating through the static solver in its own program (`design.evaluator`): one pair
    per topology and static model (contact terms, linearised strains), where the Hessian, its
    factorisation and their reverse were otherwise compiled into every configuration's forward
    and reverse pass.

    Attributes:
        residual: `(x, material, loading, q_s) -> max |dE/dq_f|` at q_s (N, N mm; the
            solve's `static_residual`, which `checked` judges: a start that is not this design's
            equilibrium).
        pullback: `(x, material, loading, q_s, w) -> w . dq_s/dx` [n_design], the
            implicit-function derivative of the equilibrium (`statics.make_static_solver`,
            `start=q_s`) pulled back from a cotangent w on it.
    """

    residual: object
    pullback: object


def static_start(scene: Scene, config: SolverConfig) -> StaticStart:
    """The `StaticStart` programs of `scene` for solves with `config` (cached)."""
    key = compile_key(scene, SolverConfig(use_contact=config.use_contact,
                                          linearized=config.linearized), "static-start", ())
    return cached_program(key, lambda: _static_start_programs(scene, config))[0]


def _static_start_programs(scene: Scene, config: SolverConfig) -> StaticStart:
    from design_engine.physics.statics import make_static_solver

    solver = make_static_solver(scene.lattice, scene.supports, use_contact=config.use_contact,
                                linearized=config.linearized, model=scene.model)

    def residual(x, material, loading, q_s):
        return solver(x, material, loading, 0.0, start=q_s)[1]["gradient_norm"]

    def pullback(x, material, loading, q_s, w):
        _, back, _ = jax.vjp(lambda z: solver(z, material, loading, 0.0, start=q_s), x,
                             has_aux=True)
        return back(w)[0]

    return StaticStart(jax.jit(residual), jax.jit(pullback))


def _simulate(scene: Scene, config: SolverConfig, ts_ms=None, loading=None, initial=None):
    ts_ms = scene.sample_times if ts_ms is None else ts_ms
    sim = compiled_simulator(scene, config, ts_ms)
    start = time.perf_counter()
    equilibrium = (static_equilibrium(scene, config)
                   if initial is None and loading is None else None)
    sol = sim(jnp.asarray(scene.design), scene.material, loading or scene.loading,
              jnp.asarray(ts_ms), initial, equilibrium)
    sol = jax.block_until_ready(sol)
    return check_solution(sol, config), time.perf_counter() - start


_CHOICES: dict[tuple, Choice] = {}


def default_choice(scene: Scene) -> Choice:
    """The automatic configuration for this scene and design (cached per process)."""
    key = compile_key(scene, SolverConfig(), "choice", np.zeros(0)) + (
        scene.design.tobytes(), float(scene.loading.strain), repr(scene.material))
    if key not in _CHOICES:
        _CHOICES[key] = choose_config(scene)
    return _CHOICES[key]


def _run_with_policy(scene: Scene, config: SolverConfig | None, ts_ms=None, loading=None):
    """Solve with `config`, or with the automatic choice under the policy driver
    (`driver.solve_with_policy`: re-solves and fallback) when None. Returns (solution, wall s,
    final config, reasons, re-solves, half-step estimate), the re-solves being the reasons of
    every solve after the first, the estimate the driver's `step_error` of the solve that
    counted (None when it was not judged so)."""
    if config is not None:
        sol, wall = _simulate(scene, config, ts_ms, loading)
        return sol, wall, config, ("configuration given by the caller",), (), None
    choice = default_choice(scene)
    walls = []

    def solve(cfg):
        sol, w = _simulate(scene, cfg, ts_ms, loading)
        walls.append(w)
        return sol, solve_health(sol, np)

    out = solve_with_policy(scene, choice.config, solve,
                            objective=lambda sol: scene_objective(scene, sol))
    return (out.result, sum(walls), out.config, choice.reasons + out.resolves, out.resolves,
            out.health.get("step_error"))


def prestressed_state(scene: Scene, config=None) -> np.ndarray:
    """State [n_blocks, 3] (mm, rad) at the end of the scene's pre-compression, when the pulse
    starts.

    A static pre-compression (`loading.is_static`) gives the equilibrium under the closed stages
    (`statics`); the two-stage ramp reaches it dynamically from rest (spec 7.4), so the state
    at t_c + t_d holds the small residual vibration of the ramp; the reference state for scenes
    without stages.
    """
    if scene.loading.strain <= 0.0:
        return np.zeros((scene.n_units, 3))
    if scene.loading.is_static:
        return static_state(scene)
    config = config or SolverConfig()
    ts = np.asarray([0.5 * scene.window_start, scene.window_start])
    sim = compiled_simulator(scene, config, ts)
    sol = check_solution(sim(jnp.asarray(scene.design), scene.material, scene.loading,
                             jnp.asarray(ts)), config)
    return np.asarray(sol.q[-1])


def simulate_scene(scene: Scene, config: SolverConfig | None = None) -> SceneRun:
    """Forward-simulate a scene on its dynamic window; raises `SimulationError` on failure.

    `config=None` uses the automatic per-scene choice (`policy.choose_config`, with fallback to
    the adaptive solver); `SolverConfig()` is the full reference model. `metrics["solver"]`
    says which configuration gave the result (`choice`: why), `resolves`: the reasons of the
    solves the policy made after its first, and `step_error` the half-step estimate when the
    policy judged the result by it (a fixed step with contact whose voids reached the cutoff).
    """
    sol, wall, config, reasons, resolves, step_error = _run_with_policy(scene, config)
    metrics = scene_metrics(scene, sol)
    metrics["solver"] = solver_stats(sol)
    metrics["solver"].update(config_summary(config))
    metrics["solver"]["choice"] = list(reasons)
    metrics["solver"]["resolves"] = list(resolves)
    if step_error is not None:  # the half-step check judged the solve that counted
        metrics["solver"]["step_error"] = float(step_error)
    return SceneRun(trajectory=to_trajectory(sol, scene.window_start, scene.sample_times),
                    solution=sol,
                    metrics=metrics, wall_s=wall)


def config_summary(config: SolverConfig) -> dict:
    """JSON-ready description of a solver configuration."""
    out = {"solver": type(config.solver).__name__, "linearized": config.linearized,
           "use_contact": config.use_contact, "dtype": config.dtype,
           **({"native_force": True} if config.native_force else {})}
    if is_fixed_step(config.solver):
        out.update(config.solver.summary())
    else:
        out.update(rtol=config.rtol, atol=config.atol, adjoint=type(config.adjoint).__name__,
                   max_steps=config.max_steps)
        if getattr(config.adjoint, "checkpoints", None) is not None:
            out.update(checkpoints=int(config.adjoint.checkpoints))
    return out


INPUT_DT_S = 1e-4  # the engine interpolates inputs linearly: resample finer than this


def smooth_input(t_s, u_m) -> tuple[np.ndarray, np.ndarray]:
    """A sampled input record made smooth for the engine's linear interpolation: records coarser
    than `INPUT_DT_S` (camera-rate tracking, 1 kHz joint states) are resampled on a cubic
    spline, whose velocity is continuous where a polyline's jumps at every sample."""
    from scipy.interpolate import CubicSpline

    t, u = np.asarray(t_s, np.float64), np.asarray(u_m, np.float64)
    t, keep = np.unique(t, return_index=True)
    u = u[keep]
    if t.size < 4 or np.median(np.diff(t)) <= INPUT_DT_S:
        return t, u
    fine = np.linspace(t[0], t[-1], int(np.ceil((t[-1] - t[0]) / INPUT_DT_S)) + 1)
    return fine, CubicSpline(t, u)(fine)


def measured_loading(scene: Scene, input_t_s, input_u_m, stage_t_s=None,
                     stage_closing_m=None) -> Loading:
    """The `Loading` of a measured experiment (SI in, validated): the shaker displacement into
    the specimen and the total stage closing (m) at times (s), linearly interpolated; no stage
    record holds the stages at zero.

    Raises:
        ValueError: arrays of unequal length, not 1-D or shorter than 2.
    """
    it, iu = np.asarray(input_t_s, np.float64), np.asarray(input_u_m, np.float64)
    if it.shape != iu.shape or it.ndim != 1 or it.size < 2:
        raise ValueError("input_t_s and input_u_m must be 1-D arrays of the same length (>= 2)")
    if stage_t_s is None:
        st, sc = np.array([0.0, 1.0]), np.zeros(2)
    else:
        st = units.time_from_si(np.asarray(stage_t_s, np.float64))
        sc = units.length_from_si(np.asarray(stage_closing_m, np.float64))
        if st.shape != sc.shape or st.ndim != 1 or st.size < 2:
            raise ValueError("stage_t_s and stage_closing_m must be 1-D arrays of equal length >= 2")
    return Loading(
        waveform="measured", amplitude=0.0, frequency=scene.loading.frequency, delay=0.0,
        pulse_start=0.0, strain=0.0, stage_height=scene.loading.stage_height,
        measured_t=jnp.asarray(units.time_from_si(it)), measured_u=jnp.asarray(units.length_from_si(iu)),
        stage_t=jnp.asarray(st), stage_closing=jnp.asarray(sc),
    )


def simulate_rig(scene: Scene, times_s, input_t_s, input_u_m, stage_t_s=None, stage_closing_m=None,
                 config: SolverConfig | None = None) -> Trajectory:
    """Simulate the specimen under measured shaker and stage motion, from rest at t = 0.

    Args:
        scene: the specimen scene (its supports say which units the shaker and stages drive).
        times_s: [n_t] increasing output times, s (> 0).
        input_t_s, input_u_m: [n] measured shaker displacement into the specimen (m) at times (s);
            linearly interpolated, held constant outside the record.
        stage_t_s, stage_closing_m: [m] measured total closing of the two stage rows (m), half per
            row; None holds the stages at zero (or is ignored in a scene without stages).
        config: solver configuration; None for the automatic choice (with fallback).

    Returns:
        SI `Trajectory` at `times_s` (time axis unchanged).
    """
    times_ms = units.time_from_si(np.asarray(times_s, np.float64))
    if times_ms.ndim != 1 or times_ms.size < 2 or np.any(np.diff(times_ms) <= 0) or times_ms[0] < 0:
        raise ValueError("times_s must be an increasing 1-D array of non-negative times")
    loading = measured_loading(scene, input_t_s, input_u_m, stage_t_s, stage_closing_m)
    sol = _run_with_policy(scene, config, times_ms, loading)[0]
    return to_trajectory(sol, 0.0, times_ms)


def make_objective(scene: Scene, config: SolverConfig | None = None, weights=None):
    """Factory: `(value_and_grad, value)` of the scene's objective, each `x -> ...`.

    `value_and_grad(x) -> ((J, aux), dJ/dx)` and `value(x) -> (J, aux)`. J (mJ, or g mm^2/ms for
    spin) is the weighted sum of the target-region energies J_Omega (spec 8; default weights 1
    for a single target, (0.5, 0.5) for two), or the angular momentum J_L for spin scenes. `aux`
    holds the solver result code, step count and void margin, so that failures can be reported
    after the jitted call (see `checked`). With a given `config` both functions are jitted as
    they are. A design's static pre-compression is solved apart, once, and handed to the solve
    (`static_equilibrium`), unless `x` is traced. `config=None` runs each call under the policy driver (`driver.solve_with_policy`):
    the automatic per-scene choice, repeated with the configuration `policy.next_config` names
    (contact once a void reached the cutoff; half the step or Dopri8 once the barrier outgrew
    the fixed step or the work-energy balance drifted; each compiled on first need), so the
    result always equals the full model's; a failed solve is retried with the fallback, and a
    failed fallback raises `SimulationError`. Each call starts where the previous one ended
    while that was in contact (`policy.start_config`). There `value_and_grad` solves as an
    optimiser does (`policy.for_gradient`) and takes the reverse pass of the solve that stands
    only (`split_gradient`, `solve_with_policy(finish=)`).
    """
    if config is not None:
        return _jitted_objective(scene, config, weights)
    programs: dict = {}
    last: dict = {"config": None, "health": None}

    def program(cfg, gradient: bool):
        """(forward, reverse) of the gradient's solve of `cfg` (`for_gradient` already applied),
        or the jitted value."""
        key = (repr(cfg), gradient)
        if key not in programs:
            programs[key] = (_split_objective(scene, cfg, weights)
                             if gradient else _objective(scene, cfg, weights, jit=True))
        return programs[key]

    def pick(gradient: bool, x):
        def solve(cfg):
            start = static_equilibrium(scene, cfg, x)
            if gradient:  # the adaptive solves as an optimiser's at this design (at the
                # scene's own where `x` is traced)
                cfg = for_gradient(cfg, scene if isinstance(x, jax.core.Tracer)
                                   else scene.with_design(np.asarray(x, np.float64)))
            out = program(cfg, gradient)[0](x, None, start) if gradient else program(
                cfg, False)(x, None, start)
            checked(out[:2], cfg)
            return (cfg, out), out[1]

        def finish(result):  # the reverse pass, for the solve that stands only
            cfg, (value, aux, pullback) = result
            return (value, aux), program(cfg, True)[1](pullback, jnp.ones_like(value))

        outcome = solve_with_policy(scene, default_choice(scene).config, solve,
                                    previous=lambda: (last["config"], last["health"]),
                                    objective=lambda result: result[1][0],
                                    finish=finish if gradient else None)
        last.update(config=outcome.config, health=outcome.health)
        return outcome.result if gradient else outcome.result[1]

    return (lambda x: pick(True, x)), (lambda x: pick(False, x))


def scene_objective(scene: Scene, sol: Solution, weights=None):
    """The scene's objective on a solution (traceable): the weighted sum of its target-region
    energies J_Omega (default weights 1 for a single target, (0.5, 0.5) for two), or the target's
    angular momentum J_L for spin scenes (see `make_objective`)."""
    names = list(scene.targets)
    if scene.spin_point is not None:
        return objective_term("angular_momentum", sol, scene.targets[names[0]], scene.spin_point)
    if weights is None:
        weights = [1.0 / len(names)] * len(names) if len(names) > 1 else [1.0]
    return sum(w * objective_term("kinetic_energy", sol, scene.targets[n])
               for w, n in zip(weights, names))


def _objective(scene: Scene, config: SolverConfig, weights, jit: bool = False):
    """The scene's objective `(x, initial=None) -> (J, aux)` (see `make_objective`)."""
    sim = make_simulator(scene.lattice, scene.supports, config, scene.sample_times,
                         model=scene.model)
    names = list(scene.targets)
    if weights is not None and len(weights) != len(names):
        raise ValueError(f"{len(names)} targets ({names}) need as many weights, got {weights}")
    ts = jnp.asarray(scene.sample_times)

    def objective(x, initial=None, equilibrium=None):
        sol = sim(x, scene.material, scene.loading, ts, initial, equilibrium)
        return scene_objective(scene, sol, weights), solve_health(sol)

    return jax.jit(objective) if jit else objective


def _jitted_objective(scene: Scene, config: SolverConfig, weights):
    objective = _objective(scene, config, weights)
    return tuple(_from_equilibrium(scene, config, fn) for fn in (
        jax.jit(jax.value_and_grad(objective, has_aux=True)), jax.jit(objective)))


def _from_equilibrium(scene: Scene, config: SolverConfig, fn):
    """`fn(x, initial=None, equilibrium=None)` as `x, initial=None -> ...`, handed the design's
    static equilibrium when it starts from one (`static_equilibrium`)."""
    def call(x, initial=None):
        return fn(x, initial, None if initial is not None else
                  static_equilibrium(scene, config, x))

    return call


def _split_objective(scene: Scene, config: SolverConfig, weights):
    return split_gradient(_objective(scene, config, weights))


def split_gradient(objective):
    """`objective(x, *rest) -> (value, aux)` as two jitted programs: the forward pass
    `(x, *rest) -> (value, aux, pullback)` and the reverse pass `(pullback, seed) -> seed x
    d value/dx`, so that a solve a policy rejects pays its forward pass only
    (`driver.solve_with_policy(finish=)`). `benchmarks/bench_reverse_split.py` measures the two
    against the fused value and gradient."""
    def forward_pass(x, *rest):
        value, pullback, aux = jax.vjp(lambda z: objective(z, *rest), x, has_aux=True)
        return value, aux, pullback

    return jax.jit(forward_pass), jax.jit(lambda pullback, seed: pullback(seed)[0])


def checked(value_aux, config: SolverConfig | None = None):
    """Raise `SimulationError` if an objective evaluation's aux (`simulate.solve_health`, plus
    anything else) reports a failure or the value is not finite."""
    (value, aux) = value_aux[0] if isinstance(value_aux[0], tuple) else value_aux
    err = simulation_error(aux, config or SolverConfig())
    if err is None and not np.isfinite(float(value)):
        err = SimulationError("non-finite objective value")
    if err is not None:
        raise err
    return value_aux


__all__ = ["SceneRun", "cached_program", "prestressed_state", "simulate_scene", "simulate_rig",
           "make_objective", "static_start", "StaticStart", "checked", "to_trajectory",
           "scene_metrics", "scene_objective", "compiled_simulator"]
