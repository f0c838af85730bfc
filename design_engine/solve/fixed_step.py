"""Fixed-step schemes for M q'' = F(q, t) - C q': their shared interface, the step grid, and
velocity Verlet (one force evaluation per step).

Every scheme is a final subclass of `AbstractFixedStep`; `simulate` and the run policies use
only that interface (`is_fixed_step` tells them from the adaptive diffrax solvers).

Every scheme keeps a work-energy ledger of its own steps (`Ledger`): kinetic plus potential
energy, minus the work the prescribed motion did, plus the work damping dissipated, is constant
for the exact motion; its largest drift over the solve, relative to the energy the solve moved
(`energy_error`), is an a-posteriori check that needs no frequency estimate (the policy in
`policy.next_config` rejects a fixed-step result above `policy.ENERGY_TOLERANCE`).

Velocity Verlet, kick-drift-kick: the first half kick treats damping explicitly, the second
implicitly (closed form, C and M diagonal), which keeps the scheme second order and symplectic
when C = 0. Explicit, so it is stable only for dt < 2 / omega_max (the highest natural
frequency, see `modal`); the contact barrier stiffens without bound, so a scene driven into
contact needs a margin or the adaptive solver. Differentiation is discretise-then-optimise
through `lax.scan`.
"""

import abc
import dataclasses
import math
from collections.abc import Callable
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np


@dataclasses.dataclass(frozen=True)
class StepGrid:
    """Static step counts of a solve from t0 = 0 through fixed sample times.

    Attributes:
        n_pre: steps from 0 to the first sample (0 when it is at 0).
        n_sub: equal steps between consecutive samples.
        n_steps: steps in all.
        dt_nominal: the largest step taken, ms.
    """

    n_pre: int
    n_sub: int
    n_steps: int
    dt_nominal: float


def step_grid(time_grid, max_dt: float) -> StepGrid:
    """Step counts for [n_t] sample times `time_grid` (ms, from t0 = 0) and steps <= `max_dt`.

    The steps before the first sample are a whole number of intervals of `n_sub` steps, so that
    `march` takes every step in one loop (one copy of the step in a compiled program): at most
    `n_sub - 1` steps more than the fewest of at most `max_dt`."""
    grid = np.asarray(time_grid, np.float64)
    n_sub = substeps(float(np.max(np.diff(grid))), max_dt)
    n_pre = n_sub * math.ceil(substeps(grid[0], max_dt) / n_sub) if grid[0] > 0 else 0
    dt_nominal = max(float(np.max(np.diff(grid))) / n_sub, float(grid[0]) / n_pre if n_pre else 0.0)
    return StepGrid(n_pre, n_sub, n_pre + n_sub * (grid.size - 1), dt_nominal)


# `integrate(force, inv_mass, damping, (q0, v0), ts) -> (q [n_t, n], v [n_t, n], converged,
# energy_error)`: force(q, t) -> (F, (V, P)) with F = -dV/dq ([n] -> [n]), V the potential energy
# and P = dV/dt at fixed q (the power the prescribed motion puts in); inv_mass, damping: [n]
# diagonals; ts: [n_t] sample times (ms) of the step grid; converged: bool scalar, False when the
# solve must be reported failed; energy_error: the ledger's verdict (`energy_error`). Optional
# keywords: a split step's fast force (`integrate`'s fast_force, fast_index), or the step's
# stages in one native call (`integrate`'s stages)
Integrator = Callable[..., tuple]


class Ledger(NamedTuple):
    """Work-energy account of a fixed-step solve (scalars, outside differentiation).

    Attributes:
        e0: kinetic + potential energy at the start.
        work: work done on the free units by the prescribed motion so far (trapezoid of P).
        dissipated: work done against damping so far (trapezoid of v . C v).
        power: P at the current step.
        drift: largest |E - e0 - work + dissipated| so far.
        moved: largest |E - e0| or |work| so far (the scale the drift is judged against).
    """

    e0: jax.Array
    work: jax.Array
    dissipated: jax.Array
    power: jax.Array
    drift: jax.Array
    moved: jax.Array


def ledger_start(v, mass, aux) -> Ledger:
    """The account at the start: state velocity `v`, diagonal `mass`, `aux` = (V, P) there."""
    potential, power = jax.lax.stop_gradient(aux)
    v = jax.lax.stop_gradient(v)
    zero = jnp.zeros((), v.dtype)
    return Ledger(0.5 * jnp.dot(v, mass * v) + potential, zero, zero, power, zero, zero)


def ledger_step(led: Ledger, dt, v, v1, mass, damping, aux1, extra_work=0.0) -> Ledger:
    """The account after a step `dt` from velocity `v` to `v1`, `aux1` = (V, P) at its end;
    `extra_work`: input work done within the step that P does not cover (the fast forces'
    prescribed-motion work of a split step, summed over its substeps)."""
    potential, power = jax.lax.stop_gradient(aux1)
    v, v1, dt, extra_work = jax.lax.stop_gradient((v, v1, dt, extra_work))
    work = led.work + 0.5 * dt * (led.power + power) + extra_work
    dissipated = led.dissipated + 0.5 * dt * (jnp.dot(v, damping * v) + jnp.dot(v1, damping * v1))
    change = 0.5 * jnp.dot(v1, mass * v1) + potential - led.e0
    drift = jnp.maximum(led.drift, jnp.abs(change - work + dissipated))
    moved = jnp.maximum(led.moved, jnp.maximum(jnp.abs(change), jnp.abs(work)))
    return Ledger(led.e0, work, dissipated, power, drift, moved)


def energy_error(led: Ledger):
    """Largest drift of the work-energy balance over the solve, relative to the energy moved (0
    when nothing moved)."""
    return jnp.where(led.moved > 0, led.drift / jnp.where(led.moved > 0, led.moved, 1.0), 0.0)


class AbstractFixedStep(eqx.Module):
    """A scheme that runs on a static step grid fitted between the sample times.

    Attributes:
        max_dt: largest step, ms.
        stability_limited: True for an explicit scheme, stable only for max_dt < 2 / omega_max
            (the policies then keep the step below that limit as the design changes).
    """

    max_dt: eqx.AbstractVar[float]
    stability_limited: eqx.AbstractClassVar[bool]

    @abc.abstractmethod
    def make_integrator(self, grid: StepGrid, bond_blocks: np.ndarray, free: np.ndarray,
                        n_dof: int) -> Integrator:
        """Factory: the pure `integrate` (see `Integrator`) for this step grid and topology.

        Args:
            grid: the step grid of the sample times.
            bond_blocks: [n_bonds, 2] units joined by each ligament.
            free: [n] increasing global indices of the integrated DOFs, out of `n_dof`.
        """

    @abc.abstractmethod
    def force_evaluations(self, num_steps: int) -> int:
        """Force evaluations of a solve of `num_steps` steps (the initial one included)."""

    @abc.abstractmethod
    def summary(self) -> dict:
        """JSON-ready settings (SI) for reports, besides the class name."""

    @abc.abstractmethod
    def unstable_hint(self) -> str:
        """Likely cause of a non-finite state, appended to the error message ("" if none)."""

    @abc.abstractmethod
    def unconverged_message(self) -> str:
        """Why a solve reported `converged = False` failed, and what to change."""

    def with_max_dt(self, max_dt: float) -> "AbstractFixedStep":
        """The same scheme with another largest step (ms)."""
        return dataclasses.replace(self, max_dt=max_dt)

    def on_grid(self, grid: StepGrid) -> "AbstractFixedStep":
        """The scheme as the programs of a solve on `grid` see it (their cache key,
        `run.compile_key`): its step the grid's, whatever step was asked for."""
        return self.with_max_dt(grid.dt_nominal)


def is_fixed_step(solver) -> bool:
    """True for a fixed-step scheme, False for an adaptive diffrax solver."""
    return isinstance(solver, AbstractFixedStep)


class FixedStepVerlet(AbstractFixedStep):
    """Velocity Verlet with at most `max_dt` (ms) per step; steps are fitted between samples.

    Attributes:
        max_dt: largest step, ms. Stability needs max_dt < 2 / omega_max (omega in rad/ms).
        remat: store each step's start state only and recompute the step in the backward pass
            instead of storing its intermediates (less memory, one more forward pass). For the
            JAX step only: a native step (`integrate`'s stages) keeps its stage forces instead.
        refined: the step is a refinement the policy took after a rejected solve
            (`policy.next_config`), which it does not refine again.
        finer_check: the policy judges this step by the same start solved at a finer step,
            not a coarser one (`policy.check_config`: the fourth order of a static
            pre-compression already in contact, whose step is STATIC_CONTACT_STEP x Verlet's).
        contact_substeps: with contact, the contact forces are stepped this many times per
            step (multiple time stepping, see `integrate`); 1 steps them with the rest.
        order: 2, velocity Verlet; 4, each step a symmetric composition of five Verlet steps
            (`SUZUKI_4`: fourth order, five force evaluations a step, stable to dt x omega_max
            = 2.72; the policy's step wherever contact is on, `policy.CONTACT_ORDER`).
    """

    max_dt: float = eqx.field(static=True, default=0.05)
    remat: bool = eqx.field(static=True, default=False)
    refined: bool = eqx.field(static=True, default=False)
    finer_check: bool = eqx.field(static=True, default=False)
    contact_substeps: int = eqx.field(static=True, default=1)
    order: int = eqx.field(static=True, default=2)
    stability_limited = True

    def __check_init__(self):
        if not self.max_dt > 0:
            raise ValueError(f"max_dt must be positive, got {self.max_dt} ms")
        if not (isinstance(self.contact_substeps, int) and self.contact_substeps >= 1):
            raise ValueError(f"contact_substeps must be a whole number >= 1, got "
                             f"{self.contact_substeps}")
        if self.order not in (2, 4):
            raise ValueError(f"order must be 2 or 4, got {self.order}")

    @property
    def splits_contact(self) -> bool:
        """True when the contact forces are stepped apart from the rest (`integrate`)."""
        return self.contact_substeps > 1

    def make_integrator(self, grid: StepGrid, bond_blocks: np.ndarray, free: np.ndarray,
                        n_dof: int) -> Integrator:
        def run(force, inv_mass, damping, y0, ts, fast_force=None, fast_index=None, stages=None):
            qs, vs, led = integrate(self, force, inv_mass, damping, y0, ts, 0.0, grid.n_pre,
                                    grid.n_sub, fast_force, fast_index, stages)
            return qs, vs, jnp.asarray(True), energy_error(led)

        return run

    def force_evaluations(self, num_steps: int) -> int:
        return num_steps * (len(SUZUKI_4) if self.order == 4 else 1) + 1

    def on_grid(self, grid: StepGrid) -> "FixedStepVerlet":
        # the policy's marks of a refined step and of its check change no program
        return dataclasses.replace(self, max_dt=grid.dt_nominal, refined=False,
                                   finer_check=False)

    def summary(self) -> dict:
        return {"max_dt_s": self.max_dt * 1e-3, **({"refined": True} if self.refined else {}),
                **({"finer_check": True} if self.finer_check else {}),
                **({"order": self.order} if self.order != 2 else {}),
                **({"remat": True} if self.remat else {}),
                **({"contact_substeps": self.contact_substeps} if self.splits_contact else {})}

    def unstable_hint(self) -> str:
        return (" (the fixed step is above the stability limit 2/omega_max, or contact stiffened "
                "the scene beyond it)")

    def unconverged_message(self) -> str:
        return "the explicit Verlet step has no iterations; it cannot fail to converge"


# Suzuki's fractal composition: Verlet steps of p, p, 1 - 4p, p, p times the step, p = 1 / (4 -
# 4^(1/3)); symmetric, so fourth order from the second-order symmetric Verlet step
_P = 1.0 / (4.0 - 4.0 ** (1.0 / 3.0))
SUZUKI_4 = (_P, _P, 1.0 - 4.0 * _P, _P, _P)
# where each of them starts within the step, fractions of it (`integrate` takes both in the
# solve's precision)
SUZUKI_4_STARTS = tuple(float(v) for v in np.cumsum((0.0,) + SUZUKI_4[:-1]))


def substeps(interval: float, max_dt: float) -> int:
    """Number of equal steps of at most `max_dt` that cover `interval` (at least 1)."""
    return max(1, math.ceil(interval / max_dt - 1e-9))


def march(step, carry, ts, t0: float, n_pre: int, n_sub: int, remat: bool = False):
    """Drive a one-step map through the sample times (shared by every fixed-step scheme).

    Args:
        step: `step(carry, t, dt) -> carry`; `carry[0], carry[1]` are the sampled q and v.
        carry: state at t0.
        ts: [n_t] sample times (the first may equal t0).
        n_pre: steps from t0 to ts[0] (static; 0 when ts[0] == t0; a multiple of n_sub,
            `step_grid`).
        n_sub: equal steps between consecutive samples (static).
        remat: store each step's start state (the carry) only, and recompute the step from it
            in the backward pass, right before its own reverse step.

    Returns:
        (carry at ts[-1], q [n_t, ...], v [n_t, ...]).
    """
    if n_pre % n_sub:
        raise ValueError(f"the steps before the first sample ({n_pre}) must be a whole number "
                         f"of intervals of {n_sub} steps")
    # remat step by step, not a sample interval at a time (which stored the intermediates of
    # all the interval's steps when it recomputed them): the reverse pass ran 24-34 % faster
    # in no more memory (benchmarks/bench_programs.py, bench_programs_step_remat.json)
    step_fn = jax.checkpoint(step) if remat else step

    def interval(c, pair):
        t_start, t_end = pair[0], pair[1]
        dt = (t_end - t_start) / n_sub

        def body(c, k):
            return step_fn(c, t_start + k * dt, dt), None

        c = jax.lax.scan(body, c, jnp.arange(n_sub, dtype=ts.dtype))[0]
        return c, (c[0], c[1])

    # one loop over intervals of n_sub steps: the n_pre / n_sub equal ones from t0 to the first
    # sample, then one per pair of samples. A second loop for the steps before the first sample
    # put a second copy of the step (and of its reverse) into every program, which XLA
    # compiled again (benchmarks/bench_programs.py)
    n_lead = n_pre // n_sub
    lead = t0 + (ts[0] - t0) * jnp.arange(n_lead, dtype=ts.dtype) / max(n_lead, 1)
    starts = jnp.concatenate([lead, ts[:-1]])
    ends = jnp.concatenate([lead[1:], ts[:1], ts[1:]]) if n_lead else ts[1:]
    last, (qs, vs) = jax.lax.scan(interval, carry, jnp.stack([starts, ends], axis=1))
    if n_lead:  # the state at the first sample is the last lead interval's
        return last, qs[n_lead - 1:], vs[n_lead - 1:]
    return last, jnp.concatenate([carry[0][None], qs]), jnp.concatenate([carry[1][None], vs])


def integrate(method: FixedStepVerlet, force, inv_mass, damping, y0, ts, t0: float, n_pre: int,
              n_sub: int, fast_force=None, fast_index=None, stages=None):
    """Integrate from t0 through the sample times.

    With `fast_force` (and `method.contact_substeps` = n > 1) the step is split by multiple
    time stepping (impulse r-RESPA): the slow forces (`force`: ligaments, damping, the
    prescribed motion) kick at the ends of the step, and in between the fast contact forces are
    stepped by n velocity-Verlet substeps of dt / n of the DOFs they act on (`fast_index`: the
    rotations), while every other DOF drifts the whole step at its velocity. The contact
    barrier's own frequency then limits the substep, not the step: the step stays at the
    ligaments' limit while a void is pressed deep into the barrier. Symmetric, so second order
    and symplectic like the plain scheme; the work-energy ledger (slow plus fast energy, the
    fast forces' input work summed over the substeps) judges it the same way.

    Args:
        method: the scheme settings.
        force: `force(q, t) -> (F, (V, P))` (see `Integrator`); with `fast_force`, the slow part.
        inv_mass, damping: [n] diagonal inverse mass and damping.
        y0: (q0, v0), each [n].
        ts: [n_t] sample times (the first may equal t0).
        n_pre: steps from t0 to ts[0] (static; 0 when ts[0] == t0).
        n_sub: steps between consecutive samples (static).
        fast_force: None, or `fast_force(q[fast_index], t) -> (F [n_fast], (V, P))` of the
            contact terms alone, which act on the DOFs `fast_index` only (static indices).
        stages: None, or `stages(q, v, f, ledger [6], t_ends [m], h [m]) -> (q1, v1, f1,
            ledger1)`: a step's m Verlet stages of lengths h ending at t_ends, the same
            arithmetic as this function's own step, in one native custom call
            (`physics.native.stages`; not with `fast_force`).

    Returns:
        (q [n_t, n], v [n_t, n]) at the sample times and the final `Ledger`.
    """
    half_c = 0.5 * inv_mass * damping
    mass = 1.0 / inv_mass
    n_fast = method.contact_substeps if fast_force is not None else 1

    if fast_force is not None:
        # the substeps move the DOFs the fast force acts on alone (`fast_index`), in vectors of
        # their own; the others drift the whole step at once, and the two are merged by a
        # gather (a scatter, and the reverse of one, took XLA's slow path). Against substeps
        # over every DOF, the fast force spread onto them: forward passes 3 % faster on 24x18 at
        # 8 % and 13 % on 6x6, reverse passes 3 % and 0 %, J the same to 6e-14
        # (benchmarks/bench_programs.py, bench_programs_fast_dofs.json)
        fast_index = np.asarray(fast_index)
        n_dof = inv_mass.shape[0]
        merge = np.arange(n_dof)
        merge[fast_index] = n_dof + np.arange(fast_index.size)
        inv_mass_fast = inv_mass[fast_index]

    def drift_and_fast_kicks(q, v, ff, t, dt):
        """The substeps between the slow half kicks: (q, v, (fast force, its (V, P)), the fast
        forces' input work) at t + dt; the fast force [n_fast] on the DOFs `fast_index`."""
        if fast_force is None:
            return q + dt * v, v, ff, 0.0
        h = dt / n_fast

        def substep(k, c):
            # a loop, not n copies of the substep: a value and gradient compiles 2-3 s faster
            # and runs 5-30 % faster, J unchanged (benchmarks/bench_programs.py, bench_substep_loop.json)
            q, v, ff, work = c
            v = v + 0.5 * h * inv_mass_fast * ff[0]
            q = q + h * v
            ff1 = fast_force(q, t + (k + 1) * h)
            v = v + 0.5 * h * inv_mass_fast * ff1[0]
            return q, v, ff1, work + 0.5 * h * (ff[1][1] + ff1[1][1])

        q_fast, v_fast, ff1, work = jax.lax.fori_loop(
            0, n_fast, substep, (q[fast_index], v[fast_index], ff, jnp.zeros_like(ff[1][1])))
        return (jnp.concatenate([q + dt * v, q_fast])[merge],
                jnp.concatenate([v, v_fast])[merge], ff1, work)

    def verlet_step(carry, t, dt):
        q, v, f, ff, led = carry
        v_half = v + 0.5 * dt * inv_mass * (f - damping * v)
        q1, v_half, ff1, fast_work = drift_and_fast_kicks(q, v_half, ff, t, dt)
        f1, aux1 = force(q1, t + dt)
        v1 = (v_half + 0.5 * dt * inv_mass * f1) / (1.0 + dt * half_c)
        if ff1 is not None:  # the ledger sees the whole potential, and the fast input work
            aux1 = (aux1[0] + ff1[1][0], aux1[1])
        return (q1, v1, f1, ff1, ledger_step(led, dt, v, v1, mass, damping, aux1, fast_work))

    fractions = SUZUKI_4 if method.order == 4 else (1.0,)  # the stages' lengths, of the step

    def native_step(carry, t, dt):  # its ledger an array [6] from step to step
        q, v, f, ff, led = carry
        q1, v1, f1, led1 = stages(q, v, f, led,
                                  t + jnp.asarray(np.cumsum(fractions), dt.dtype) * dt,
                                  jnp.asarray(fractions, dt.dtype) * dt)
        return q1, v1, f1, ff, led1

    def step(carry, t, dt):
        if stages is not None:
            return native_step(carry, t, dt)
        if method.order == 2:
            return verlet_step(carry, t, dt)
        # the five Verlet steps as a loop, not unrolled: one copy of the step (and of its
        # reverse) in the program. Value and gradient of the 24x18 protection scene at 8 %:
        # first call 16.0-16.3 s against 18.7-21.4 s, the second the same, 5.4-5.8 against
        # 5.3-5.5 s (benchmarks/bench_order4_program.py -> bench_order4_program_amd.json)
        lengths = jnp.asarray(SUZUKI_4, dt.dtype)
        starts = jnp.asarray(SUZUKI_4_STARTS, dt.dtype)
        return jax.lax.fori_loop(
            0, len(SUZUKI_4),
            lambda k, c: verlet_step(c, t + starts[k] * dt, lengths[k] * dt), carry)

    q0, v0 = y0
    t_start = jnp.asarray(t0, ts.dtype)
    f0, aux0 = force(q0, t_start)
    ff0 = fast_force(q0[fast_index], t_start) if fast_force is not None else None
    if ff0 is not None:
        aux0 = (aux0[0] + ff0[1][0], aux0[1])
    led0 = ledger_start(v0, mass, aux0)
    carry = (q0, v0, f0, ff0, led0 if stages is None else jnp.stack(led0))
    # the native step is not recomputed in the reverse pass (`remat` is for the JAX step): it
    # keeps its stage forces, 5 vectors a step, and its reverse reads them. Value and gradient
    # of the 8 % design 13: 2.78-2.83 s against 3.29-3.40 s recomputed, 0.94 against 0.70 GB
    # at the peak (benchmarks/bench_native_stages.py -> bench_native_stages_fvp13_amd.json)
    last, qs, vs = march(step, carry, ts, t0, n_pre, n_sub, method.remat and stages is None)
    return qs, vs, last[4] if stages is None else Ledger(*last[4])
