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
through `lax.scan`. The step counts are run-time arguments (`march`): one compiled program
serves every step whose counts fit its capacity (`step_capacity`).
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


class StepGrid(NamedTuple):
    """Step counts of a solve from t0 = 0 through fixed sample times.

    On the host the fields are Python numbers; a compiled solve takes them as run-time arrays
    (`Integrator`), so that one program serves every step up to its `step_capacity`.

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
    """Step counts for [n_t] sample times `time_grid` (ms, from t0 = 0) and steps <= `max_dt`."""
    grid = np.asarray(time_grid, np.float64)
    n_pre = substeps(grid[0], max_dt) if grid[0] > 0 else 0
    n_sub = substeps(float(np.max(np.diff(grid))), max_dt)
    dt_nominal = max(float(np.max(np.diff(grid))) / n_sub, float(grid[0]) / n_pre if n_pre else 0.0)
    return StepGrid(n_pre, n_sub, n_pre + n_sub * (grid.size - 1), dt_nominal)


def capacity(n: int) -> int:
    """The smallest of 1, 2, 3, 4, 6, 8, 12, 16, 24, ... (2^k and 3 x 2^k) that is >= n (0 for
    0): a compiled solve holds this many steps per interval, so a step that changes by a few
    per cent (a design's new frequency, the policy's refinement) keeps its program, and at
    most a third of the steps a program holds go unused (skipped, not computed)."""
    if n <= 0:
        return 0
    power = 1 << (n - 1).bit_length()  # the smallest power of two >= n
    return 3 * power // 4 if power >= 4 and 3 * power // 4 >= n else power


def step_capacity(grid: StepGrid) -> StepGrid:
    """The static step counts a compiled solve is built for: `capacity` of each of `grid`'s
    (n_steps and dt_nominal as for those counts, for the record)."""
    n_pre, n_sub = capacity(grid.n_pre), capacity(grid.n_sub)
    n_t = (grid.n_steps - grid.n_pre) // grid.n_sub + 1
    return StepGrid(n_pre, n_sub, n_pre + n_sub * (n_t - 1), 0.0)


def run_time_steps(grid: StepGrid, dtype) -> StepGrid:
    """`grid` as the run-time argument of a compiled solve (int32 counts, `dtype` step)."""
    return StepGrid(jnp.asarray(grid.n_pre, jnp.int32), jnp.asarray(grid.n_sub, jnp.int32),
                    jnp.asarray(grid.n_steps, jnp.int32), jnp.asarray(grid.dt_nominal, dtype))


# `integrate(force, inv_mass, damping, (q0, v0), ts, steps) -> (q [n_t, n], v [n_t, n],
# converged, energy_error)`: force(q, t) -> (F, (V, P)) with F = -dV/dq ([n] -> [n]), V the
# potential energy and P = dV/dt at fixed q (the power the prescribed motion puts in); inv_mass,
# damping: [n] diagonals; ts: [n_t] sample times (ms); steps: the run-time `StepGrid` of those
# times (`run_time_steps`), within the capacity the integrator was made for; converged: bool
# scalar, False when the solve must be reported failed; energy_error: the ledger's verdict
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


def ledger_step(led: Ledger, dt, v, v1, mass, damping, aux1) -> Ledger:
    """The account after a step `dt` from velocity `v` to `v1`, `aux1` = (V, P) at its end."""
    potential, power = jax.lax.stop_gradient(aux1)
    v, v1, dt = jax.lax.stop_gradient((v, v1, dt))
    work = led.work + 0.5 * dt * (led.power + power)
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
    """A scheme that runs on a step grid fitted between the sample times: its step counts are
    run-time arguments up to a static capacity (`step_capacity`), so one compiled program
    serves every step of a bucket (`program_form`).

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
        """Factory: the pure `integrate` (see `Integrator`) for this capacity and topology.

        Args:
            grid: the static step counts the solve can hold (`step_capacity`); each call's
                run-time counts must be within them.
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

    @abc.abstractmethod
    def program_form(self) -> "AbstractFixedStep":
        """The scheme with its run-time settings (the step, bookkeeping flags) set to fixed
        values: two schemes of equal `program_form` and equal `step_capacity` compile to the
        same program."""

    def with_max_dt(self, max_dt: float) -> "AbstractFixedStep":
        """The same scheme with another largest step (ms)."""
        return dataclasses.replace(self, max_dt=max_dt)


def is_fixed_step(solver) -> bool:
    """True for a fixed-step scheme, False for an adaptive diffrax solver."""
    return isinstance(solver, AbstractFixedStep)


class FixedStepVerlet(AbstractFixedStep):
    """Velocity Verlet with at most `max_dt` (ms) per step; steps are fitted between samples.

    Attributes:
        max_dt: largest step, ms. Stability needs max_dt < 2 / omega_max (omega in rad/ms).
        remat: recompute the steps between two samples in the backward pass instead of storing
            them (less memory, one more forward pass).
        refined: the step is a refinement the policy took after a rejected solve
            (`policy.next_config`), which it does not refine again.
    """

    max_dt: float = eqx.field(static=True, default=0.05)
    remat: bool = eqx.field(static=True, default=False)
    refined: bool = eqx.field(static=True, default=False)
    stability_limited = True

    def __check_init__(self):
        if not self.max_dt > 0:
            raise ValueError(f"max_dt must be positive, got {self.max_dt} ms")

    def make_integrator(self, grid: StepGrid, bond_blocks: np.ndarray, free: np.ndarray,
                        n_dof: int) -> Integrator:
        def run(force, inv_mass, damping, y0, ts, steps):
            qs, vs, led = integrate(self, force, inv_mass, damping, y0, ts, 0.0, steps, grid)
            return qs, vs, jnp.asarray(True), energy_error(led)

        return run

    def program_form(self) -> "FixedStepVerlet":
        return dataclasses.replace(self, max_dt=1.0, refined=False)

    def force_evaluations(self, num_steps: int) -> int:
        return num_steps + 1

    def summary(self) -> dict:
        return {"max_dt_s": self.max_dt * 1e-3, **({"refined": True} if self.refined else {}),
                **({"remat": True} if self.remat else {})}

    def unstable_hint(self) -> str:
        return (" (the fixed step is above the stability limit 2/omega_max, or contact stiffened "
                "the scene beyond it)")

    def unconverged_message(self) -> str:
        return "the explicit Verlet step has no iterations; it cannot fail to converge"


def substeps(interval: float, max_dt: float) -> int:
    """Number of equal steps of at most `max_dt` that cover `interval` (at least 1)."""
    return max(1, math.ceil(interval / max_dt - 1e-9))


def march(step, carry, ts, t0: float, steps: StepGrid, capacity: StepGrid, remat: bool = False):
    """Drive a one-step map through the sample times (shared by every fixed-step scheme).

    Each interval runs a scan over its capacity whose steps beyond the run-time count are
    skipped (`lax.cond`: not computed, forward or reverse), so the count is an argument.

    Args:
        step: `step(carry, t, dt) -> carry`; `carry[0], carry[1]` are the sampled q and v.
        carry: state at t0.
        ts: [n_t] sample times (the first may equal t0).
        steps: run-time `StepGrid`: n_pre steps from t0 to ts[0] (0 when ts[0] == t0), n_sub
            equal steps between consecutive samples.
        capacity: static `StepGrid` (`step_capacity`) >= `steps`; n_pre = 0 leaves out the
            steps before ts[0].
        remat: recompute the steps between two samples in the backward pass.

    Returns:
        (carry at ts[-1], q [n_t, ...], v [n_t, ...]).
    """

    def advance(carry, t_start, t_end, n, cap):
        # times the reciprocal, as XLA's simplifier computed a division by the static count
        dt = (t_end - t_start) * (1.0 / jnp.asarray(n, ts.dtype))

        def body(c, k):
            return jax.lax.cond(k < n, lambda c: step(c, t_start + k * dt, dt), lambda c: c,
                                c), None

        return jax.lax.scan(body, carry, jnp.arange(cap, dtype=ts.dtype))[0]

    if capacity.n_pre > 0:
        carry = advance(carry, jnp.asarray(t0, ts.dtype), ts[0], steps.n_pre, capacity.n_pre)
    first = carry

    def interval(c, pair):
        advance_fn = jax.checkpoint(advance, static_argnums=(4,)) if remat else advance
        c = advance_fn(c, pair[0], pair[1], steps.n_sub, capacity.n_sub)
        return c, (c[0], c[1])

    last, (qs, vs) = jax.lax.scan(interval, carry, jnp.stack([ts[:-1], ts[1:]], axis=1))
    return last, jnp.concatenate([first[0][None], qs]), jnp.concatenate([first[1][None], vs])


def integrate(method: FixedStepVerlet, force, inv_mass, damping, y0, ts, t0: float,
              steps: StepGrid, capacity: StepGrid):
    """Integrate from t0 through the sample times.

    Args:
        method: the scheme settings.
        force: `force(q, t) -> (F, (V, P))` (see `Integrator`).
        inv_mass, damping: [n] diagonal inverse mass and damping.
        y0: (q0, v0), each [n].
        ts: [n_t] sample times (the first may equal t0).
        steps, capacity: run-time step counts and the static capacity (`march`).

    Returns:
        (q [n_t, n], v [n_t, n]) at the sample times and the final `Ledger`.
    """
    half_c = 0.5 * inv_mass * damping
    mass = 1.0 / inv_mass

    def step(carry, t, dt):
        q, v, f, led = carry
        v_half = v + 0.5 * dt * inv_mass * (f - damping * v)
        q1 = q + dt * v_half
        f1, aux1 = force(q1, t + dt)
        v1 = (v_half + 0.5 * dt * inv_mass * f1) / (1.0 + dt * half_c)
        return (q1, v1, f1, ledger_step(led, dt, v, v1, mass, damping, aux1))

    q0, v0 = y0
    f0, aux0 = force(q0, jnp.asarray(t0, ts.dtype))
    carry = (q0, v0, f0, ledger_start(v0, mass, aux0))
    last, qs, vs = march(step, carry, ts, t0, steps, capacity, method.remat)
    return qs, vs, last[3]
