"""What the pieces of a force evaluation cost on XLA's CPU backend, side by side in one process.

Each piece runs inside a `lax.scan` of `--iterations` iterations (as in a Verlet solve), and the
per-iteration wall time is the median over `--repeats` interleaved rounds (every piece is timed
once per round, so that a change of load falls on all of them alike):
- atan2 of the 728 bonds' shear angles (24x16 units): `jnp.arctan2` against `angles.atan2`;
- wrapping the 1456 void angles onto [-pi, pi): `jnp.mod` against `energy.wrap` (floor);
- the contact energy and its gradient: from the state [n_blocks, 3] through the bond map
  (`make_energy`, contact term only) against `make_contact_energy` (rotations alone);
- the force evaluation (energy and gradient) of the whole model without and with contact, the
  slow and fast forces of a split step (`FixedStepVerlet.contact_substeps`);
- the reverse of those force evaluations (the product of the Hessian with a vector, as a fixed
  step's reverse pass takes it: `jax.vjp` of the force);
- the same force evaluations and reverses by the native custom calls (`physics.native`, in
  float64 and float32, against XLA's float32 too), where they can be built here.
Writes OUT/NAME.json (default bench_force_pieces.json; per piece: median and min us per
iteration, machine, load). Run from another checkout's source to time its code with this
script (`git worktree add DIR REF`, then `PYTHONPATH=DIR python benchmarks/...`: the file
records which `design_engine` it timed, `source`).

    .venv/bin/python benchmarks/bench_force_pieces.py --out benchmarks/results
"""

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

from machine import describe, source_checkout

HERE = Path(__file__).resolve().parent


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=Path("runs/bench-force-pieces"))
    p.add_argument("--iterations", type=int, default=2000)
    p.add_argument("--repeats", type=int, default=7)
    p.add_argument("--name", default="bench_force_pieces", help="output file name, no suffix")
    args = p.parse_args(argv)

    import jax
    import jax.numpy as jnp

    import design_engine  # noqa: F401  (float64)
    from design_engine.design.design_io import load_design
    from design_engine.physics import energy as E
    from design_engine.physics.angles import atan2
    from design_engine.physics.geometry import block_geometry
    from design_engine.physics.scenes import build_scene

    lattice, x = load_design(HERE / "results" / "design_focusing-24x16.json")
    scene = build_scene("focusing-24x16", nx=lattice.shape[0], ny=lattice.shape[1], design=x)
    bonds = E.bond_geometry(lattice, block_geometry(lattice, jnp.asarray(x)))
    mat = scene.material
    rng = np.random.default_rng(0)
    nb, n_bonds = lattice.n_blocks, lattice.bond_blocks.shape[0]
    q0 = jnp.asarray(rng.normal(scale=1e-3, size=(nb, 3)))
    pairs = jnp.asarray(rng.normal(size=(n_bonds, 2)))
    voids = jnp.asarray(rng.normal(size=(n_bonds, 2)))

    def energy_force(fn):
        return lambda q: q + 1e-9 * jax.grad(lambda z: fn(z, bonds, mat))(q)

    direction = jnp.asarray(rng.normal(scale=1e-3, size=(nb, 3)))

    def hessian_product(fn):
        def force(z):
            return jax.grad(lambda y: fn(y, bonds, mat))(z)

        return lambda q: q + 1e-9 * jax.vjp(force, q)[1](direction)[0]

    contact_of_state = E.make_energy(
        lattice, model=E.Model(ligament=lambda m, _: {}, contact=E.contact_law))
    contact_of_rotations = E.make_contact_energy(lattice)
    pieces = {
        "atan2 728, jnp.arctan2": (lambda a: a + 1e-9 * jnp.arctan2(a[:, 0], a[:, 1])[:, None],
                                   pairs),
        "atan2 728, angles.atan2": (lambda a: a + 1e-9 * atan2(a[:, 0], a[:, 1])[:, None], pairs),
        "wrap 1456, jnp.mod": (lambda a: jnp.mod(a + np.pi, 2 * np.pi) - np.pi + 1e-9, voids),
        "wrap 1456, energy.wrap": (lambda a: E.wrap(a) + 1e-9, voids),
        "contact energy + gradient, from the state": (energy_force(contact_of_state), q0),
        "contact energy + gradient, from the rotations (fast force)": (
            lambda th: th + 1e-9 * jax.grad(lambda z: contact_of_rotations(z, bonds, mat))(th),
            q0[:, 2]),
        "force, no contact (slow force)": (
            energy_force(E.make_energy(lattice, use_contact=False)), q0),
        "force, with contact": (energy_force(E.make_energy(lattice)), q0),
        "force reverse (Hessian product), no contact": (
            hessian_product(E.make_energy(lattice, use_contact=False)), q0),
        "force reverse (Hessian product), with contact": (
            hessian_product(E.make_energy(lattice)), q0),
    }
    from design_engine.physics.native.build import NativeUnavailable, library

    try:
        library()
    except NativeUnavailable as exc:
        print(f"native rows left out: {exc}")
    else:
        from design_engine.physics.native.force import (make_contact_energy_and_gradient,
                                                        make_energy_and_gradient)

        def native_force(fn, cast):
            return lambda q: q + 1e-9 * fn(q, cast, mat)[1]

        def native_reverse(fn, cast, d):
            return lambda q: q + 1e-9 * jax.vjp(lambda z: fn(z, cast, mat)[1], q)[1](d)[0]

        for dtype in ("float64", "float32"):
            cast = jax.tree.map(lambda a, t=dtype: a.astype(t), bonds)
            q_t, d_t = q0.astype(dtype), direction.astype(dtype)
            both, slow = make_energy_and_gradient(lattice), make_energy_and_gradient(
                lattice, use_contact=False)
            fast = make_contact_energy_and_gradient(lattice)
            pieces.update({
                f"native force, with contact, {dtype}": (native_force(both, cast), q_t),
                f"native force, no contact (slow force), {dtype}": (native_force(slow, cast), q_t),
                f"native contact force from the rotations (fast force), {dtype}": (
                    lambda th, f=fast, c=cast: th + 1e-9 * f(th, c, mat)[1], q_t[:, 2]),
                f"native force reverse (Hessian product), with contact, {dtype}": (
                    native_reverse(both, cast, d_t), q_t),
            })
            if dtype == "float32":
                pieces.update({
                    "force, with contact, float32": (
                        lambda q, c=cast: q + 1e-9 * jax.grad(
                            lambda z: E.make_energy(lattice)(z, c, mat))(q), q_t),
                    "force reverse (Hessian product), with contact, float32": (
                        lambda q, c=cast, d=d_t: q + 1e-9 * jax.vjp(jax.grad(
                            lambda z: E.make_energy(lattice)(z, c, mat)), q)[1](d)[0], q_t),
                })

    def program(body, init):
        run = jax.jit(lambda c: jax.lax.scan(lambda s, _: (body(s), None), c, None,
                                             length=args.iterations)[0])
        jax.block_until_ready(run(init))

        def timed():
            t0 = time.perf_counter()
            jax.block_until_ready(run(init))
            return (time.perf_counter() - t0) / args.iterations * 1e6

        return timed

    programs = {name: program(*piece) for name, piece in pieces.items()}
    load0 = os.getloadavg()
    times = {name: [] for name in programs}
    for _ in range(args.repeats):
        for name, timed in programs.items():
            times[name].append(timed())
    rows = {name: {"median_us": float(np.median(t)), "min_us": float(np.min(t))}
            for name, t in times.items()}
    for name, r in rows.items():
        print(f"{name:<62} {r['median_us']:8.1f} us (min {r['min_us']:.1f})")
    args.out.mkdir(parents=True, exist_ok=True)
    report = {"machine": describe(), "source": source_checkout(),
              "load_average_start": load0,
              "load_average_end": os.getloadavg(), "units": nb, "bonds": n_bonds,
              "iterations": args.iterations, "repeats": args.repeats, "pieces": rows}
    (args.out / f"{args.name}.json").write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
