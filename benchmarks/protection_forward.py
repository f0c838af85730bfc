"""The protection scene's forward solve as the per-step benchmarks time it (imported by
bench_step_thunks.py and bench_pinned_workers.py): 24x18 at 8 %, the policy's configuration,
from the design's static equilibrium at rest, through the first `samples` sample times."""


def protection_forward(samples: int):
    """`(solve, x, q_s, steps, config)`: the jitted (not yet compiled) `solve(x, q_s)`
    returning the positions at the sample times, its arguments, how many fixed steps it takes
    and the configuration."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    import design_engine  # noqa: F401  (float64)
    from design_engine.physics.scenes import build_scene
    from design_engine.solve.fixed_step import step_grid
    from design_engine.solve.policy import choose_config
    from design_engine.solve.run import static_equilibrium
    from design_engine.solve.simulate import make_simulator

    scene = build_scene("protection-24x18", strain=0.08)
    config = choose_config(scene).config
    times = np.asarray(scene.sample_times)[:samples]
    steps = step_grid(times, config.solver.max_dt).n_steps
    sim = make_simulator(scene.lattice, scene.supports, config, times, model=scene.model)
    x = jnp.asarray(scene.design)
    q_s = jnp.asarray(static_equilibrium(scene, config, x))
    ts = jnp.asarray(times)
    solve = jax.jit(lambda x, q: sim(x, scene.material, scene.loading, ts,
                                     (q, jnp.zeros_like(q))).q)
    return solve, x, q_s, steps, config
