"""Static equilibrium under prescribed displacements, with implicit-function gradients.

The quasi-static alternative to simulating a pre-compression ramp (issue 12, item 2): the
stages close slowly and the rig settles before the pulse, so the state the pulse starts from is
the minimum of the elastic energy (ligaments and contact) over the free DOFs with the
prescribed DOFs at their values at time `t_hold` (stages closed, input at rest).

Solver: load continuation (the prescribed values scaled by lambda from 0 to 1 in steps that move
no prescribed DOF by more than MAX_LOAD_STEP_MM and are at most 1 / n_load; a level whose
Newton solve does not converge within `newton_iters` is retried at half the step from the last
equilibrium, and the step grows back by half per converged level; each level starts from the
secant predictor through the last two equilibria when its energy is finite there, else from the
last equilibrium), and at each load level damped Newton on the free DOFs with the exact
Hessian, (H + mu I) d = -g, mu raised tenfold until the energy falls and stays finite and no void
passes the contact asymptote (past it the barrier's energy is zero again, so the energy alone
would not stop a step there), and lowered threefold after a success, until max |g| <=
GRADIENT_TOL at the full load (LEVEL_TOL at the levels before it). The Hessian is exact and
sparse: one Hessian-vector product per colour and DOF of a distance-2 colouring of the bond
graph (21 products for the 1146 free DOFs of 24x18; `make_sparse_hessian`); the solves are block
Cholesky factorisations in the Hessian's banded order (`linalg.make_sparse_spd_solve`), which
read the blocks they need from the products and add mu on the diagonal themselves: the Hessian
is never a dense matrix (warm equilibria of the focus-vs-protect scenes, 24x18 at 1 % and 8 %,
then took 1.3-2.1x less time, to the same bits: `benchmarks/bench_static_solve.py`).

The step bound is a margin for the branch a slow loading follows. A pre-compressed lattice has
several equilibria under the same stage closing, and a coarse continuation may land on another
branch than the one the stages reach. With the secant predictor and the asymptote check, on the
24x18 protection scene at 8 %, 8, 32, 48, 64 and 100 equal levels all end at 525.371 mJ, the
equilibrium that the dynamic ramp settles into (its end state relaxed by Newton: 525.371 mJ;
at 5 %, 225.439 mJ both): `benchmarks/bench_statics.py --parts branches`. With the bound of
0.1 mm the continuation takes 103 levels there.

Gradients: the returned state is q_s + (s - stop_gradient(s)), s = -H_s^-1 g(q_s; theta), with
q_s and H_s held constant: its value is exactly q_s and its derivative with respect to any
input theta (design, material, loading) is the implicit one, dq*/dtheta = -H^-1 dg/dtheta,
exact at an equilibrium. `info["gradient_norm"]` says how close to one the solve came.
Internal units (mm, rad, N mm).
"""

import threading

import jax
import jax.numpy as jnp
import numpy as np

from design_engine.physics.energy import (DEFAULT_MODEL, Model, bond_geometry, followed_voids,
                                          make_energy)
from design_engine.physics.geometry import block_geometry
from design_engine.physics.lattice import Lattice
from design_engine.physics.linalg import implicit_point, make_sparse_spd_solve
from design_engine.physics.loading import Loading, Supports, make_prescribed

N_LOAD = 8  # fewest load levels of the continuation
MAX_LOAD_STEP_MM = 0.1  # largest change of any prescribed DOF per load level, mm (see above)
MAX_LEVELS = 600  # most load levels tried, converged or not
LOAD_GROWTH = 1.5  # step factor after a converged level (0.5 after a failed one), up to the bound
MIN_LOAD_STEP = 1e-5  # the continuation gives up below this step of lambda
NEWTON_ITERS = 40  # most damped Newton iterations per load level
GRADIENT_TOL = 1e-10  # converged when max |dE/dq_f| is below this (N, N mm)
# the continuation's intermediate load levels only carry the branch to the next level's
# predictor, so they stop at this residual; the full load is solved to GRADIENT_TOL. On the
# designs of two 20-evaluation focus-vs-protect runs at 1 % and 8 %, 1e-2 reached the same
# equilibria as 1e-6 (within 6e-12 mm/rad) in 0.5-0.6x the time at 8 %, and on those of two
# more runs (one from a seeded start) 1e-1 reached those of 1e-2 through the same levels
# (within 1.6e-9) in 0.77-0.78x the time at 8 %:
# `benchmarks/bench_statics.py --parts bound --bounds "" --level-tols 1e-2,1e-1 --run R`
LEVEL_TOL = 1e-1
DESIGN_LEVELS = 12  # most levels of a continuation in the design (`follow_design`)
MAX_DAMPING_TRIES = 12  # tenfold increases of mu before a step is given up
MIN_DAMPING, MAX_DAMPING = 1e-12, 1e3  # bounds of mu (relative to the largest Hessian diagonal)


class EquilibriumError(RuntimeError):
    """The static solve did not reach an equilibrium (one line saying how far it stayed)."""


def check_equilibrium(info: dict, tol: float = 100 * GRADIENT_TOL) -> dict:
    """Raise `EquilibriumError` unless the solve's max |dE/dq_f| is finite and below `tol`
    (N, N mm); returns `info` (call it outside jit, on the solver's info)."""
    g = float(info["gradient_norm"])
    if not (np.isfinite(g) and g <= tol):
        raise EquilibriumError(
            f"the static pre-compression did not converge: max |dE/dq| = {g:.3g} (tolerance "
            f"{tol:.1g}); more load levels (n_load) or Newton iterations (newton_iters) may help, "
            "unless the equilibrium handed to the solve (equilibrium=, start=) was another "
            "design's")
    return info


def distance2_colouring(n_blocks: int, bond_blocks: np.ndarray) -> np.ndarray:
    """[n_blocks] colours such that two blocks of one colour share no bond and no neighbour
    (greedy, distance-2 on the bond graph)."""
    nbrs = [set() for _ in range(n_blocks)]
    for a, b in np.asarray(bond_blocks):
        nbrs[int(a)].add(int(b))
        nbrs[int(b)].add(int(a))
    colour = np.full(n_blocks, -1, np.int64)
    for b in range(n_blocks):
        near = set(nbrs[b])
        for c in nbrs[b]:
            near |= nbrs[c]
        used = {int(colour[c]) for c in near if colour[c] >= 0}
        colour[b] = next(k for k in range(n_blocks + 1) if k not in used)
    return colour


def make_sparse_hessian(lattice: Lattice, free: np.ndarray, grad_fn):
    """Factory: `hessian(q_f, *args) -> [n_free, n_free]` of the energy whose gradient is
    `grad_fn(q_f, *args)`, from one Hessian-vector product per (colour, DOF) seed instead of
    one per DOF: each bond's energy depends on its two blocks only, so columns of blocks of
    one distance-2 colour touch disjoint rows (`distance2_colouring`). The static solver uses
    the products themselves, `hessian.products(q_f, *args) -> [n_seeds, n_free]` (column j on
    the pattern's rows is product `hessian.seed_of[j]`), and never the dense matrix."""
    free = np.asarray(free)
    block, dof = free // 3, free % 3
    colour = distance2_colouring(lattice.n_blocks, lattice.bond_blocks)
    seed_of = colour[block] * 3 + dof  # [n_free] the seed whose product holds column j
    n_seeds = int(seed_of.max()) + 1
    seeds = np.zeros((n_seeds, free.size))
    seeds[seed_of, np.arange(free.size)] = 1.0
    near = [{b} for b in range(lattice.n_blocks)]
    for a, b in np.asarray(lattice.bond_blocks):
        near[int(a)].add(int(b))
        near[int(b)].add(int(a))
    rows_of_block = {}
    for j, b in enumerate(block):
        rows_of_block.setdefault(int(b), []).append(j)
    ii, jj = [], []
    for j in range(free.size):
        for b in near[int(block[j])]:
            rows = rows_of_block.get(b, [])
            ii.extend(rows)
            jj.extend([j] * len(rows))
    ii, jj = np.asarray(ii), np.asarray(jj)
    ss = seed_of[jj]

    def products(q, *args):
        """[n_seeds, n_free] the Hessian-vector products: column j of the Hessian is product
        `seed_of[j]` on the rows of the pattern (what `linalg.make_sparse_spd_solve(...,
        seed_of=)` solves with, no dense matrix built)."""
        def hvp(v):
            return jax.jvp(lambda z: grad_fn(z, *args), (q,), (v,))[1]

        return jax.vmap(hvp)(jnp.asarray(seeds, q.dtype))

    def hessian(q, *args):
        prods = products(q, *args)
        return jnp.zeros((free.size, free.size), q.dtype).at[ii, jj].set(prods[ss, ii])

    hessian.products = products
    hessian.seed_of = seed_of
    hessian.n_seeds = n_seeds
    hessian.pattern = (ii, jj)  # where its nonzeros lie
    return hessian


def make_static_solver(lattice: Lattice, supports: Supports, *, use_contact: bool = True,
                       linearized: bool = False, n_load: int = N_LOAD,
                       newton_iters: int = NEWTON_ITERS, level_tol: float = LEVEL_TOL,
                       max_load_step_mm: float = MAX_LOAD_STEP_MM,
                       model: Model = DEFAULT_MODEL):
    """Factory: `equilibrium(x, material, loading, t_hold) -> (q_f [n_free], info)` (jit/grad).

    `level_tol`: the residual max |dE/dq_f| at which the load levels before the full load stop
    (the full load is always solved to GRADIENT_TOL). `max_load_step_mm`: the largest change of
    any prescribed DOF per load level (module docstring).

    Args of the returned function:
        x: [n_design] design vector, mm.
        material: `Material`; loading: `Loading`.
        t_hold: time (ms) whose prescribed values are held (e.g. the end of the stage ramp,
            before the pulse).
        guess: optional (x_from [n_design], q_from [n_free]): a nearby design and its
            equilibrium's free DOFs (an optimiser's previous design, mm / rad; not
            differentiated). The equilibrium is then followed from there to `x` at the full
            load, by a continuation in the design (`follow_design`: the whole change first,
            halved where Newton fails); the load continuation runs only when that does not
            reach `x` within DESIGN_LEVELS levels. "levels" is then minus the design levels
            taken. It follows the equilibrium the previous design was on, which need not be
            the one the stages reach: along a focus-vs-protect run's designs at 8 % it took
            0.24-2.4 s against 10-13 s and reached the load continuation's equilibrium 3 times
            in 4, the fourth 2.1 mm/rad off (`benchmarks/bench_statics.py --parts warm`), so
            the solver policy does not use it.
        start: optional [n_free] this design's equilibrium, already found (by this solver,
            compiled apart, e.g. `equilibrium_state`; not differentiated): taken as it is, with
            no Newton step and no load level ("levels" 0, "damping" 0), and differentiated
            like a solved one; "gradient_norm" is its residual, so a start that is not this
            design's equilibrium fails `check_equilibrium` (never a silent answer). A caller
            that needs the equilibrium before a solve that differentiates through it (the
            design loop's step check, `run.simulate_scene`) so solves it once, in one program
            per topology, and the solve's own program holds no Newton solver or continuation:
            the forward pass (value and pullback, the policy's configuration) of the 24x18
            protection scene at 8 % compiles in 6.6 s with a start against 8.6 s solving the
            equilibrium itself, and runs in 0.60 against 1.47 s (the static solver, compiled
            once: 3.5 s; `benchmarks/bench_compile.py`, 2 cores).

    Returns q_f (the free DOFs at equilibrium, mm / rad, in `supports.free` order;
    differentiable by the implicit function theorem) and info (not differentiated):
    "gradient_norm" = max |dE/dq_f| at the solution under the full load (N, N mm), "energy"
    (mJ), "damping" (the last Newton damping mu, relative to the largest Hessian diagonal),
    "load" (the lambda reached, 1 when complete) and "levels" (load levels tried).
    """
    energy_fn = make_energy(lattice, use_contact=use_contact, linearized=linearized, model=model)
    values, _ = make_prescribed(supports)
    n_free = int(np.asarray(supports.free).size)
    index = np.asarray(supports.assemble_index)
    nb = lattice.n_blocks

    def total(qf, qc, bonds, material):
        q = jnp.concatenate([qf, qc])[index].reshape(nb, 3)
        return energy_fn(q, bonds, material)

    def admissible(qf, qc, bonds, material):
        """No void past the contact asymptote (beyond it the barrier's energy is zero again,
        spec 5.3, so an energy test alone would let a step jump through the barrier)."""
        if not use_contact:
            return jnp.asarray(True)
        q = jnp.concatenate([qf, qc])[index].reshape(nb, 3)
        voids = followed_voids(bonds.void_ref, q, lattice.bond_blocks)
        return jnp.min(voids) > material.contact_min

    grad = jax.grad(total)
    hessian = make_sparse_hessian(lattice, np.asarray(supports.free), grad)
    hess = hessian.products  # the Hessian as its products; `_solve` reads what it needs of them
    # Cholesky in the Hessian's banded order (6x less than the dense one on 24x18)
    _solve = make_sparse_spd_solve(n_free, *hessian.pattern, seed_of=hessian.seed_of)
    diagonal = (np.asarray(hessian.seed_of), np.arange(n_free))  # its entries in the products

    def newton(q, mu, qc, bonds, material, tol=GRADIENT_TOL):
        """Damped Newton at fixed prescribed values qc, until max |g| <= tol or
        `newton_iters` steps: (q, mu, converged)."""
        def step(carry):
            q, mu, k, _ = carry
            e0 = total(q, qc, bonds, material)
            g = grad(q, qc, bonds, material)
            h = hess(q, qc, bonds, material)
            scale = jnp.maximum(jnp.max(jnp.abs(h[diagonal])), 1e-30)
            slack = 1e-13 * jnp.abs(e0)  # rounding: a converged step may not lower E

            def attempt(state):
                m, _, _, tries = state
                d = _solve(h, -g, m * scale)
                e1 = total(q + d, qc, bonds, material)
                ok = (jnp.isfinite(e1) & (e1 <= e0 + slack) & jnp.all(jnp.isfinite(d))
                      & admissible(q + d, qc, bonds, material))
                return jnp.where(ok, m, m * 10.0), d, ok, tries + 1

            def again(state):
                return (~state[2]) & (state[3] < MAX_DAMPING_TRIES)

            m, d, ok, _ = jax.lax.while_loop(
                again, attempt, (mu, jnp.zeros_like(q), jnp.asarray(False), jnp.asarray(0)))
            q = jnp.where(ok, q + d, q)
            mu = jnp.clip(jnp.where(ok, m / 3.0, mu), MIN_DAMPING, MAX_DAMPING)
            return q, mu, k + 1, jnp.max(jnp.abs(grad(q, qc, bonds, material)))

        def more(carry):
            return (carry[3] > tol) & (carry[2] < newton_iters)

        q, mu, _, gnorm = jax.lax.while_loop(
            more, step, (q, mu, jnp.asarray(0), jnp.asarray(jnp.inf, q.dtype)))
        return q, mu, gnorm <= tol

    def continuation(qc_s, bonds, material, dtype):
        """Adaptive load stepping from lambda = 0 to 1 (see module docstring)."""
        def level(carry):
            q, q_prev, lam, lam_prev, dlam, mu, k = carry
            target = jnp.minimum(lam + dlam, 1.0)
            qc = target * qc_s
            secant = q + (q - q_prev) * (target - lam) / jnp.maximum(lam - lam_prev, 1e-30)
            use = (jnp.isfinite(total(secant, qc, bonds, material)) & (lam > 0)
                   & admissible(secant, qc, bonds, material))
            q_new, mu_new, ok = newton(jnp.where(use, secant, q), mu, qc, bonds, material,
                                       jnp.where(target < 1.0, level_tol, GRADIENT_TOL))
            ok = ok & jnp.all(jnp.isfinite(q_new)) & admissible(q_new, qc, bonds, material)
            return (jnp.where(ok, q_new, q), jnp.where(ok, q, q_prev),
                    jnp.where(ok, target, lam), jnp.where(ok, lam, lam_prev),
                    jnp.where(ok, jnp.minimum(LOAD_GROWTH * dlam, dlam_max), 0.5 * dlam),
                    jnp.where(ok, mu_new, mu), k + 1)

        def more(carry):
            lam, dlam, k = carry[2], carry[4], carry[6]
            return (lam < 1.0) & (dlam >= MIN_LOAD_STEP) & (k < MAX_LEVELS)

        zero = jnp.zeros(n_free, dtype)
        dlam_max = jnp.minimum(1.0 / n_load,
                               max_load_step_mm / jnp.maximum(jnp.max(jnp.abs(qc_s)), 1e-30))
        start = (zero, zero, jnp.asarray(0.0, dtype), jnp.asarray(0.0, dtype),
                 dlam_max.astype(dtype), jnp.asarray(1e-8, dtype), jnp.asarray(0))
        q, _, lam, _, _, mu, k = jax.lax.while_loop(more, level, start)
        return q, mu, lam, k

    def constants(x, loading, t_hold):
        bonds = bond_geometry(lattice, block_geometry(lattice, x))
        return values(jnp.asarray(t_hold, x.dtype), loading), bonds

    def follow_design(x_from, q_from, x_to, qc, ms, dtype):
        """Continuation in the design at the full load: from the equilibrium `q_from` of design
        `x_from` to design `x_to`, in steps of the design's change (the whole change first,
        halved after a level that fails, grown by LOAD_GROWTH after one that converges), each
        damped Newton from the tangent predictor (the implicit function's derivative along the
        change, which turns the units with the voids the design moves). Returns (q, mu,
        reached, levels): reached when it got to `x_to` within DESIGN_LEVELS levels."""
        def bonds_at(lam):
            return bond_geometry(lattice, block_geometry(lattice, x_from + lam * (x_to - x_from)))

        def tangent(q, lam):
            """dq/dlam along the equilibrium: -H^-1 d(dE/dq)/dlam (implicit function)."""
            _, dg = jax.jvp(lambda a: grad(q, qc, bonds_at(a), ms), (lam,),
                            (jnp.ones_like(lam),))
            return -_solve(hess(q, qc, bonds_at(lam), ms), dg)

        def level(carry):
            q, t, lam, dlam, mu, k = carry
            target = jnp.minimum(lam + dlam, 1.0)
            bonds = bonds_at(target)
            guess = q + (target - lam) * t  # the tangent predictor
            good = (jnp.all(jnp.isfinite(guess)) & jnp.isfinite(total(guess, qc, bonds, ms))
                    & admissible(guess, qc, bonds, ms))
            q_new, mu_new, ok = jax.lax.cond(  # no Newton from a state past the asymptote
                good, lambda: newton(guess, mu, qc, bonds, ms),
                lambda: (q, mu, jnp.asarray(False)))
            ok = (ok & jnp.all(jnp.isfinite(q_new))
                  & admissible(q_new, qc, bonds, ms))
            q_next = jnp.where(ok, q_new, q)
            lam_next = jnp.where(ok, target, lam)
            t_next = jax.lax.cond(ok & (lam_next < 1.0), lambda: tangent(q_next, lam_next),
                                  lambda: t)
            return (q_next, t_next, lam_next,
                    jnp.where(ok, jnp.minimum(LOAD_GROWTH * dlam, 1.0), 0.5 * dlam),
                    jnp.where(ok, mu_new, mu), k + 1)

        def more(carry):
            lam, dlam, k = carry[2], carry[3], carry[5]
            return (lam < 1.0) & (dlam >= MIN_LOAD_STEP) & (k < DESIGN_LEVELS)

        zero = jnp.asarray(0.0, dtype)
        start = (q_from, tangent(q_from, zero), zero, jnp.asarray(1.0, dtype),
                 jnp.asarray(1e-8, dtype), jnp.asarray(0))
        q, _, lam, _, mu, k = jax.lax.while_loop(more, level, start)
        return q, mu, lam >= 1.0, k

    def from_guess(guess, qc_s, xs, bonds_s, ms, dtype):
        """The equilibrium followed from a nearby design's (`follow_design`), else the load
        continuation (see `equilibrium`; `bonds_s`: those of `xs`). Returns (q, mu, lam,
        levels)."""
        x_from, q_from = (jnp.asarray(a, dtype) for a in guess)
        usable = jnp.all(jnp.isfinite(x_from)) & jnp.all(jnp.isfinite(q_from))
        q_w, mu_w, ok, k = follow_design(jnp.where(usable, x_from, xs),
                                         jnp.where(usable, q_from, 0.0), xs, qc_s, ms, dtype)
        ok = usable & ok
        return jax.lax.cond(
            ok, lambda: (q_w, mu_w, jnp.asarray(1.0, dtype), -k),
            lambda: continuation(qc_s, bonds_s, ms, dtype))

    def equilibrium(x, material, loading: Loading, t_hold, guess=None, start=None):
        x = jnp.asarray(x)
        xs, ms, ls = jax.lax.stop_gradient((x, material, loading))
        qc_s, bonds_s = constants(xs, ls, t_hold)

        if start is not None:  # taken as it is (see above): the residual below judges it
            q_s, mu, lam, levels = (jnp.asarray(start, x.dtype), jnp.asarray(0.0, x.dtype),
                                    jnp.asarray(1.0, x.dtype), jnp.asarray(0))
        elif guess is None:
            q_s, mu, lam, levels = continuation(qc_s, bonds_s, ms, x.dtype)
        else:
            q_s, mu, lam, levels = from_guess(jax.lax.stop_gradient(guess), qc_s, xs, bonds_s,
                                              ms, x.dtype)
        q_s = jax.lax.stop_gradient(q_s)
        h = jax.lax.stop_gradient(hess(q_s, qc_s, bonds_s, ms))
        def step(x, material, loading):
            qc, bonds = constants(x, loading, t_hold)
            return -_solve(h, grad(q_s, qc, bonds, material))

        q = implicit_point(q_s, step, x, material, loading)
        # a continuation that stopped short of lambda = 1 reports the residual at full load
        residual = jnp.max(jnp.abs(grad(q_s, qc_s, bonds_s, ms)))
        info = {"gradient_norm": jnp.where(jnp.isfinite(residual), residual, jnp.inf),
                "energy": total(q_s, qc_s, bonds_s, ms), "damping": mu, "load": lam,
                "levels": levels}
        return q, jax.lax.stop_gradient(info)

    return equilibrium


_SOLVERS: dict[tuple, object] = {}  # jitted solvers of this process, per topology
# the last equilibria found (`equilibrium_state`), or the message of a solve that failed
_STATES: dict[tuple, np.ndarray | str] = {}
KEEP_STATES = 16  # how many
_STATES_LOCK = threading.Lock()  # the design loop solves scenes on several threads


def forget_equilibria() -> None:
    """Drop the equilibria `equilibrium_state` keeps: a timing that repeats a solve of one
    design then pays its static solve every time, as a new design does."""
    _STATES.clear()


def equilibrium_state(scene) -> np.ndarray:
    """[n_blocks, 3] state (mm, rad) of a static pre-compression scene (`scenes.Scene`): the
    equilibrium under its closed stages with the prescribed DOFs filled in, as the pulse starts
    from it (one compiled solver per lattice and supports; the last `KEEP_STATES` results are
    kept, failures too, so the policy's frequency check and the solve after it, or a design's
    re-solves, do not solve it again). Raises `EquilibriumError` when the solve does not
    converge."""
    lat, sup = scene.lattice, scene.supports
    key = (lat.shape, lat.n_blocks, np.asarray(lat.bond_blocks).tobytes(),
           sup.constrained.tobytes(), sup.channel.tobytes(), sup.gain.tobytes(), scene.model)
    leaves, tree = jax.tree_util.tree_flatten((scene.design, scene.material, scene.loading))
    inputs = key + (str(tree), tuple(np.asarray(a).tobytes() for a in leaves))
    with _STATES_LOCK:
        found = _STATES.get(inputs)
    if found is None:
        found = _solve_state(scene, key)
        with _STATES_LOCK:
            while len(_STATES) >= KEEP_STATES:
                del _STATES[next(iter(_STATES))]  # the oldest
            _STATES[inputs] = found
    if isinstance(found, str):
        raise EquilibriumError(found)
    return found.copy()


def _solve_state(scene, key: tuple) -> np.ndarray | str:
    """`equilibrium_state`'s solve: the state, or the message of the solve's failure."""
    if key not in _SOLVERS:
        _SOLVERS[key] = jax.jit(make_static_solver(scene.lattice, scene.supports,
                                                   model=scene.model))
    q_f, info = _SOLVERS[key](jnp.asarray(scene.design), scene.material, scene.loading, 0.0)
    try:
        check_equilibrium(info)
    except EquilibriumError as exc:
        return str(exc)
    values, _ = make_prescribed(scene.supports)
    q = np.zeros(3 * scene.n_units)
    q[scene.supports.free] = np.asarray(q_f)
    q[scene.supports.constrained] = np.asarray(values(jnp.asarray(0.0), scene.loading))
    return q.reshape(-1, 3)
