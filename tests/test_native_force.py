"""The native bond force (`design_engine.physics.native`) against the JAX energy it implements:
values, gradients, the reverse pass (Hessian products and design and material derivatives), the
contact force of a split step, and a whole fixed-step solve's J and gradient."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from design_engine.physics import energy as E
from design_engine.physics.geometry import block_geometry
from design_engine.physics.lattice import kagome, periodic_design, quads
from design_engine.physics.material import Material
from design_engine.physics.native import build


@pytest.fixture(scope="module")
def native():
    try:
        build.library()
    except build.NativeUnavailable as exc:
        pytest.skip(f"native bond force unavailable here: {exc}")
    from design_engine.physics.native import force

    return force


MATERIAL = Material(k_stretch=120.0, k_shear=1.19, k_bend=1.5, k_contact=1.5,
                    contact_min=np.radians(-15.0), contact_cutoff=np.radians(-10.0),
                    density=1e-3, damping_u=0.0, damping_theta=0.0)


def _case(lattice, bias_deg, seed=0):
    """(design x, a state [n_blocks, 3] that closes many voids into the contact band)."""
    x = jnp.asarray(periodic_design(lattice, np.radians(bias_deg)))
    rng = np.random.default_rng(seed)
    nb = lattice.n_blocks
    # rotating squares close their voids by turning alternately: the turn that puts the most
    # voids between the asymptote and the cutoff, then a little noise on every unit
    cell = lattice.cell_of_block
    sign = np.where((cell[:, 0] + cell[:, 1]) % 2 == 0, 1.0, -1.0)

    ref = np.asarray(_bonds(lattice, x).void_ref)
    bb = lattice.bond_blocks

    def in_band(turn):
        bend = (sign[bb[:, 1]] - sign[bb[:, 0]]) * turn
        v = np.asarray(E.wrap(ref + np.stack([-bend, bend], axis=1)))
        return int(np.sum((v >= MATERIAL.contact_min) & (v < MATERIAL.contact_cutoff)))

    turns = np.radians(np.linspace(-80.0, 80.0, 641))
    turn = turns[int(np.argmax([in_band(t) for t in turns]))]
    q = np.zeros((nb, 3))
    q[:, 2] = sign * turn + rng.normal(scale=np.radians(0.3), size=nb)
    q[:, :2] = rng.normal(scale=0.05, size=(nb, 2))
    return x, jnp.asarray(q)


def _bonds(lattice, x):
    return E.bond_geometry(lattice, block_geometry(lattice, x))


def _voids_in_band(lattice, x, q, mat=MATERIAL):
    v = np.asarray(E.make_bond_measures(lattice)(q, _bonds(lattice, x)).voids)
    return int(np.sum((v >= mat.contact_min) & (v < mat.contact_cutoff)))


LATTICES = {"quads 6x5": (lambda: quads(6, 5), 20.0), "kagome 3x3": (lambda: kagome(3, 3), 0.0)}


@pytest.mark.parametrize("name", LATTICES)
@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_the_native_force_is_the_jax_energy_and_its_gradient(native, name, dtype):
    make, bias = LATTICES[name]
    lattice = make()
    x, q = _case(lattice, bias)
    if name.startswith("quads"):
        assert _voids_in_band(lattice, x, q) >= 10  # the barrier is exercised, not only the law
    bonds = _bonds(lattice, x)
    cast = jax.tree.map(lambda a: a.astype(dtype), bonds)
    for contact in (True, False):
        jax_energy = E.make_energy(lattice, use_contact=contact)
        e_ref, g_ref = jax.value_and_grad(jax_energy)(q, bonds, MATERIAL)
        e, g = native.make_energy_and_gradient(lattice, use_contact=contact)(
            q.astype(dtype), cast, MATERIAL)
        assert e.dtype == g.dtype == jnp.dtype(dtype)
        scale = float(jnp.max(jnp.abs(g_ref)))
        if dtype == "float64":
            e_tol, g_tol = 1e-12 * abs(float(e_ref)), 1e-12 * scale
        else:  # as close to the float64 values as JAX's own float32 energy comes
            e32, g32 = jax.value_and_grad(jax_energy)(q.astype(dtype), cast, MATERIAL)
            e_tol = 4.0 * abs(float(e32) - float(e_ref)) + 1e-7 * abs(float(e_ref))
            g_tol = 4.0 * float(jnp.max(jnp.abs(g32 - g_ref))) + 1e-7 * scale
        assert abs(float(e) - float(e_ref)) <= e_tol
        assert float(jnp.max(jnp.abs(g - g_ref))) <= g_tol


def test_the_native_reverse_pass_is_the_hessian_product_and_the_design_and_material_derivative(
        native):
    lattice = quads(6, 5)
    x, q = _case(lattice, 20.0, seed=1)
    assert _voids_in_band(lattice, x, q) >= 10
    lam = jnp.asarray(np.random.default_rng(2).normal(size=q.shape))
    jax_energy = E.make_energy(lattice)
    fast = native.make_energy_and_gradient(lattice)

    def scalar(value_and_grad):  # what a reverse pass through a force sees: both outputs used
        def s(q, x, mat):
            e, g = value_and_grad(q, _bonds(lattice, x), mat)
            return 0.3 * e + jnp.sum(g * lam)

        return jax.grad(s, argnums=(0, 1, 2))

    ref = scalar(jax.value_and_grad(jax_energy))(q, x, MATERIAL)
    got = scalar(fast)(q, x, MATERIAL)
    for a, b in zip(ref[:2], got[:2]):  # the state (Hessian product) and the design
        assert float(jnp.max(jnp.abs(a - b))) <= 1e-10 * float(jnp.max(jnp.abs(a)))
    for field in native.LIGAMENT_FIELDS + native.CONTACT_FIELDS:
        a, b = float(getattr(ref[2], field)), float(getattr(got[2], field))
        assert a != 0.0 and abs(a - b) <= 1e-10 * abs(a), field

    # a sample's material, one value per bond (hardware_sim.specimen.imperfect)
    rng = np.random.default_rng(3)
    n = lattice.n_bonds
    per_bond = eqx.tree_at(lambda m: (m.k_shear, m.k_contact), MATERIAL,
                           (jnp.asarray(MATERIAL.k_shear * rng.uniform(0.9, 1.1, n)),
                            jnp.asarray(MATERIAL.k_contact * rng.uniform(0.9, 1.1, n))))
    ref = scalar(jax.value_and_grad(jax_energy))(q, x, per_bond)
    got = scalar(fast)(q, x, per_bond)
    for field in ("k_shear", "k_contact"):
        a, b = getattr(ref[2], field), getattr(got[2], field)
        assert a.shape == (n,)
        assert float(jnp.max(jnp.abs(a - b))) <= 1e-10 * float(jnp.max(jnp.abs(a)))


def test_the_native_contact_force_of_the_rotations_matches_the_jax_one(native):
    lattice = quads(6, 5)
    x, q = _case(lattice, 20.0, seed=4)
    bonds = _bonds(lattice, x)
    order = np.random.default_rng(5).permutation(lattice.n_blocks)  # as a split step holds them
    theta = jnp.zeros(lattice.n_blocks).at[order].set(q[:, 2])
    lam = jnp.asarray(np.random.default_rng(6).normal(size=theta.shape))
    jax_fn = jax.value_and_grad(E.make_contact_energy(lattice, order=order))
    fast = native.make_contact_energy_and_gradient(lattice, order=order)

    def reverse(fn):
        return jax.grad(lambda t, x, mat: (lambda e, g: 0.3 * e + jnp.sum(g * lam))(
            *fn(t, _bonds(lattice, x), mat)), argnums=(0, 1, 2))(theta, x, MATERIAL)

    (e_ref, g_ref), (e, g) = jax_fn(theta, bonds, MATERIAL), fast(theta, bonds, MATERIAL)
    assert float(e_ref) > 0.0
    assert abs(float(e) - float(e_ref)) <= 1e-12 * float(e_ref)
    assert float(jnp.max(jnp.abs(g - g_ref))) <= 1e-12 * float(jnp.max(jnp.abs(g_ref)))
    ref, got = reverse(jax_fn), reverse(fast)
    for a, b in zip(ref[:2], got[:2]):
        assert float(jnp.max(jnp.abs(a - b))) <= 1e-10 * float(jnp.max(jnp.abs(a)))
    for field in native.CONTACT_FIELDS:
        a, b = float(getattr(ref[2], field)), float(getattr(got[2], field))
        assert abs(a - b) <= 1e-10 * abs(a), field


def test_the_native_force_maps_over_a_batch_of_states(native):
    lattice = quads(4, 4)
    x, q = _case(lattice, 20.0, seed=7)
    bonds = _bonds(lattice, x)
    fn = native.make_energy_and_gradient(lattice)
    qs = jnp.stack([q, 0.5 * q])
    e, g = jax.vmap(lambda z: fn(z, bonds, MATERIAL))(qs)
    for k in range(2):
        e_k, g_k = fn(qs[k], bonds, MATERIAL)
        assert float(e[k]) == float(e_k) and bool(jnp.all(g[k] == g_k))


@pytest.mark.parametrize("method", ["verlet", "dopri8"])
def test_a_solve_in_contact_with_native_forces_gives_the_jax_solve_s_value_and_gradient(native,
                                                                                        method):
    import diffrax

    from design_engine.physics.scenes import build_scene
    from design_engine.solve.fixed_step import FixedStepVerlet
    from design_engine.solve.run import make_objective
    from design_engine.solve.simulate import SolverConfig

    # 6x6 at 7 %: the static pre-compression closes voids past the cutoff, so the pulse runs in
    # contact from the start; the fixed step with the contact forces split off and substepped,
    # Dopri8 as the design loop's fallback solves it
    scene = build_scene("protection-24x18", nx=6, ny=6, strain=0.07, amplitude_m=2e-3)
    x = jnp.asarray(scene.design)
    solver = (FixedStepVerlet(max_dt=0.02, remat=True, contact_substeps=4) if method == "verlet"
              else diffrax.Dopri8())
    out = {}
    for flag in (False, True):
        config = SolverConfig(solver=solver, native_force=flag, rtol=1e-11, atol=1e-10)
        value_and_grad, _ = make_objective(scene, config)
        (j, aux), g = value_and_grad(x)
        assert int(aux["result"]) == 0 and float(aux["start_void_margin"]) < float(
            scene.material.contact_cutoff - scene.material.contact_min)
        out[flag] = (float(j), np.asarray(g))
    (j0, g0), (j1, g1) = out[False], out[True]
    # the fixed steps see the same force to rounding; Dopri8's controller picks its steps from
    # rounding-level differences, so the two agree within the solver's own error, which these
    # tolerances keep small: 2e-6 apart in the gradient here (at rtol 1e-10 and atol 1e-8 each
    # was 3e-5 and 6e-5 from this solve)
    j_tol, g_tol = (1e-10, 1e-7) if method == "verlet" else (1e-10, 2e-5)
    assert j0 > 0.0 and abs(j1 - j0) <= j_tol * j0
    assert np.linalg.norm(g1 - g0) <= g_tol * np.linalg.norm(g0)


@pytest.mark.parametrize("order,dtype", [(4, "float64"), (2, "float64"), (4, "float32")])
def test_a_solve_by_the_native_verlet_stages_is_the_jax_step_s(native, monkeypatch, order, dtype):
    from design_engine.physics.scenes import build_scene
    from design_engine.solve import simulate
    from design_engine.solve.fixed_step import FixedStepVerlet
    from design_engine.solve.run import make_objective
    from design_engine.solve.simulate import SolverConfig

    # 6x6 at 7 %: in contact from the static pre-compression on; the policy's schemes there
    # (the fourth order) and at rest (Verlet, float32), each step one native call
    scene = build_scene("protection-24x18", nx=6, ny=6, strain=0.07, amplitude_m=2e-3)
    x = jnp.asarray(scene.design)
    config = SolverConfig(solver=FixedStepVerlet(max_dt=0.015 if order == 4 else 0.006,
                                                 order=order, remat=True),
                          native_force=True, dtype=dtype)
    made = []
    native_stages = simulate.make_verlet_stages
    monkeypatch.setattr(simulate, "make_verlet_stages",
                        lambda *a, **k: made.append(1) or native_stages(*a, **k))
    out = {}
    for stages in (True, False):
        if not stages:  # the JAX step around the same native force
            monkeypatch.setattr(simulate, "make_verlet_stages", lambda *a, **k: None)
        (j, aux), g = make_objective(scene, config)[0](x)
        assert int(aux["result"]) == 0
        out[stages] = (float(j), np.asarray(g), float(aux["energy_error"]))
    assert made  # the first solve did run the native stages
    (j1, g1, e1), (j0, g0, e0) = out[True], out[False]
    assert j0 > 0.0 and 0.0 < e0 < 1e-3
    if dtype == "float64":  # the same arithmetic to rounding
        assert abs(j1 - j0) <= 1e-10 * j0
        assert np.linalg.norm(g1 - g0) <= 1e-8 * np.linalg.norm(g0)
        assert abs(e1 - e0) <= 1e-6 * e0
    else:  # float32 rounding in another order: within float32's own error of the solve
        assert abs(j1 - j0) <= 2e-4 * j0
        assert np.linalg.norm(g1 - g0) <= 1e-2 * np.linalg.norm(g0)
        assert abs(e1 - e0) <= 1e-5


def test_the_native_verlet_stages_reverse_pass_is_their_derivative(native):
    from jax.test_util import check_grads

    from design_engine.physics.dynamics import make_dynamics_args
    from design_engine.physics.loading import make_prescribed
    from design_engine.physics.native.stages import make_verlet_stages
    from design_engine.physics.scenes import build_scene
    from design_engine.solve.fixed_step import SUZUKI_4
    from design_engine.solve.simulate import static_state

    # a state in contact (the 4x4 scene's static pre-compression at 7 %), moving: the
    # derivative of a fourth-order step in every input it differentiates, against central
    # differences
    scene = build_scene("protection-24x18", nx=4, ny=4, strain=0.07, amplitude_m=2e-3)
    lattice, supports = scene.lattice, scene.supports
    free = np.asarray(supports.free)
    state = np.asarray(static_state(scene)).reshape(-1)
    args = make_dynamics_args(lattice, supports, block_geometry(lattice, jnp.asarray(scene.design)),
                              scene.material, scene.loading)
    packed = native.make_energy_and_gradient(lattice).pack(args.bonds, args.material, jnp.float64)
    step = make_verlet_stages(lattice, supports)
    rng = np.random.default_rng(4)
    n_free = free.size
    q = jnp.asarray(state[free])
    v = jnp.asarray(rng.normal(scale=0.05, size=n_free))
    f = jnp.asarray(rng.normal(scale=0.1, size=n_free))
    dt = 0.01
    h = jnp.asarray(SUZUKI_4) * dt
    ends = jnp.cumsum(h)
    _, prescribed = make_prescribed(supports)
    qc, qcd = jax.vmap(lambda t: prescribed(t, scene.loading))(0.3 + ends)
    damping = args.damping + 0.2  # some damping, so that its terms count
    ledger = jnp.zeros(6)

    def f_step(q, v, f, arms, vref, lig, con, inv_mass, damping, qc):
        q1, v1, f1, _ = step(q, v, f, ledger, (arms, vref, lig, con), inv_mass, damping, qc,
                             qcd, h)
        return q1, v1, f1

    inputs = (q, v, f, *packed, args.inv_mass, damping, qc)
    for i in range(len(inputs)):  # one input at a time, so that no term hides behind another
        def f_one(a, i=i):
            return f_step(*inputs[:i], a, *inputs[i + 1:])

        check_grads(f_one, (inputs[i],), order=1, modes=["rev"], eps=1e-5, atol=1e-7, rtol=1e-6)


def test_forward_mode_solves_keep_the_jax_force():
    import diffrax

    from design_engine.physics.energy import DEFAULT_MODEL
    from design_engine.solve.simulate import SolverConfig, _native

    config = SolverConfig(solver=diffrax.Dopri8(), native_force=True)
    assert not _native(dataclasses.replace(config, adjoint=diffrax.ForwardMode()), DEFAULT_MODEL)
    assert not _native(dataclasses.replace(config, native_force=False), DEFAULT_MODEL)
    assert not _native(dataclasses.replace(config, linearized=True), DEFAULT_MODEL)


def test_a_machine_without_a_compiler_is_told_why_in_one_line(monkeypatch):
    monkeypatch.setenv("CXX", "no-such-compiler-here")
    with pytest.raises(build.NativeUnavailable, match=r"^no C\+\+ compiler \(no-such-compiler-here\)"):
        build._build()


def test_a_configuration_that_asks_for_native_forces_says_so_in_its_summary():
    from design_engine.solve.fixed_step import FixedStepVerlet
    from design_engine.solve.run import config_summary
    from design_engine.solve.simulate import SolverConfig

    config = SolverConfig(solver=FixedStepVerlet(max_dt=0.02), native_force=True)
    assert config_summary(config)["native_force"] is True
    assert "native_force" not in config_summary(dataclasses.replace(config, native_force=False))
