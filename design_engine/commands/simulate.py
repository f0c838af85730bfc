"""`metarig simulate` and `metarig modes`: run a preset scene and write its outputs (SI)."""

import argparse
import json
import logging
import math
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from metarig.argtypes import positive

log = logging.getLogger("metarig.simulate")


def _scene_args(p: argparse.ArgumentParser) -> None:
    from design_engine.physics.scenes import PRESETS

    p.add_argument("--preset", default="focusing-24x16", choices=list(PRESETS),
                   help="scene of the paper to simulate")
    p.add_argument("--nx", type=int, help="units (kagome: cells) along x; default the preset's")
    p.add_argument("--ny", type=int, help="units (kagome: cells) along y; default the preset's")
    p.add_argument("--bias-angle-deg", type=float, help="bias angle of the periodic design, degrees "
                   "(default 25; kagome 0)")
    p.add_argument("--amplitude", type=float, help="input amplitude, m (default half the spacing)")
    p.add_argument("--frequency", type=float, default=30.0, help="input frequency, Hz")
    p.add_argument("--precompression", type=float, help="pre-compression strain of stage scenes "
                   "(e.g. 0.02)")
    p.add_argument("--ramp", action="store_true", help="simulate the reference's dynamic "
                   "pre-compression ramp instead of starting the pulse from the static "
                   "equilibrium under the closed stages (the default)")
    p.add_argument("--design", type=Path, help="design file (JSON, metarig-design/1) to simulate "
                   "instead of the periodic design")
    p.add_argument("--samples", type=int, help="samples in the dynamic window (default 200)")
    p.add_argument("--task", help="task preset or task file: simulate its first scene (with "
                   "--design, that design) and report the task's objectives as `metarig design` "
                   "optimises them")
    p.add_argument("--material", type=Path, help="material file (TOML, metarig-material/1, SI) "
                   "replacing the scene's default material (README 'Material files')")


def _with_material(args, scene):
    """The scene with the material of `--material` (if given)."""
    if getattr(args, "material", None) is None:
        return scene
    from design_engine.physics.material_file import with_material

    return with_material(scene, args.material)


def _build(args):
    from design_engine.design.design_io import load_design
    from design_engine.physics.scenes import build_scene

    design = None
    nx, ny = args.nx, args.ny
    if getattr(args, "task", None) == "":
        raise ValueError("--task is empty; give a task preset or a task file")
    for flag, v in (("--nx", nx), ("--ny", ny)):  # None: not given (0 is no lattice size)
        if v is not None and v < 2:
            raise ValueError(f"{flag} must be at least 2 (a lattice needs 2x2 units), got {v}")
    if args.design is not None:
        lattice, design = load_design(args.design)
        if (nx is not None and nx != lattice.shape[0]) or \
                (ny is not None and ny != lattice.shape[1]):
            raise ValueError(f"--nx/--ny disagree with the design file's lattice {lattice.shape}")
        nx, ny = lattice.shape
    if getattr(args, "task", None) is not None:
        task = _task(args, nx, ny, design)
        return task.scenes[task.terms[0].scene]
    if args.samples is not None and args.samples < 2:
        raise ValueError("--samples must be at least 2")
    return _with_material(args, build_scene(
        args.preset, nx=nx, ny=ny, bias_angle_deg=args.bias_angle_deg, amplitude_m=args.amplitude,
        frequency_hz=args.frequency, strain=args.precompression, design=design,
        n_samples=args.samples, precompression="ramp" if args.ramp else "static"))


def _task(args, nx, ny, design):
    """The task of `--task`, on the design's lattice, with the design in every scene."""
    from design_engine.design.task import load_task

    if (nx is None) != (ny is None):  # one of --nx/--ny: the other from the task
        shape = load_task(args.task).lattice.shape
        nx, ny = shape[0] if nx is None else nx, shape[1] if ny is None else ny
    task = load_task(args.task, size=None if nx is None else (nx, ny),
                     bias_angle_deg=args.bias_angle_deg, material=getattr(args, "material", None))
    if design is not None:
        if design.size != task.lattice.n_design:
            raise ValueError(f"the design does not fit the task's {task.lattice.kind} lattice")
        task = replace(task, scenes={k: s.with_design(design) for k, s in task.scenes.items()})
    return task


def task_summary(task, main_scene: str, main_solution, config) -> dict:
    """The task's objectives on the scene designs (other scenes simulated with `config`)."""
    from design_engine.design.evaluator import task_terms
    from design_engine.solve.run import simulate_scene

    sols = {main_scene: main_solution}
    for t in task.terms:
        if t.scene not in sols:
            sols[t.scene] = simulate_scene(task.scenes[t.scene], config).solution
    terms = task_terms(task, sols)
    return {"name": task.name, "goal": task.goal, "objective": task.scalarised_si(terms),
            "objectives": task.objectives_si(terms), "metrics": task.metrics(terms)}


SOLVERS = ("auto", "dopri5", "tsit5", "dopri8", "verlet", "newmark")


def _config(args):
    """SolverConfig from the flags, or None for the automatic per-scene choice."""
    import diffrax

    from design_engine.solve.fixed_step import FixedStepVerlet
    from design_engine.solve.implicit_step import ImplicitNewmark
    from design_engine.solve.simulate import SolverConfig

    for flag, v in (("--rtol", args.rtol), ("--atol", args.atol)):
        if not (math.isfinite(v) and v >= 0):
            raise ValueError(f"{flag} must be a finite number >= 0, got {v}")
    model = dict(linearized=args.linearized, use_contact=not args.no_contact,
                 dtype="float32" if args.float32 else "float64",
                 progress=not args.quiet and sys.stderr.isatty())
    if args.full_model:
        return SolverConfig(progress=model["progress"])
    if args.solver == "auto":
        if args.linearized or args.no_contact or args.float32:
            raise ValueError("--linearized/--no-contact/--float32 need an explicit --solver")
        return None
    if args.solver == "verlet":
        return SolverConfig(solver=FixedStepVerlet(max_dt=args.max_dt * 1e3), **model)
    if args.solver == "newmark":
        return SolverConfig(solver=ImplicitNewmark(max_dt=args.max_dt * 1e3,
                                                   iterations=args.iterations), **model)
    solver = {"dopri5": diffrax.Dopri5(), "tsit5": diffrax.Tsit5(), "dopri8": diffrax.Dopri8()}
    return SolverConfig(solver=solver[args.solver], rtol=args.rtol, atol=args.atol, **model)


def simulate_main(argv: list[str] | None = None) -> int:
    """Simulate a scene; write summary.json, trajectory.npz, design.json and PNG plots to --out."""
    p = argparse.ArgumentParser(prog="metarig simulate", description=simulate_main.__doc__,
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    _scene_args(p)
    p.add_argument("--out", type=Path, default=None, help="output folder (default runs/<preset>)")
    p.add_argument("--solver", choices=SOLVERS, default="auto",
                   help="auto: fixed-step Verlet at a step set from the measured highest natural "
                   "frequency away from contact, adaptive Dopri8 in contact or on failure; "
                   "newmark: implicit trapezoidal Newmark (chord iterations)")
    p.add_argument("--full-model", action="store_true", help="force the reference configuration "
                   "(Dopri5, rtol 1e-8, atol 1e-4, float64, nonlinear strains, contact)")
    p.add_argument("--rtol", type=float, default=1e-8, help="relative tolerance (adaptive solvers)")
    p.add_argument("--atol", type=float, default=1e-4, help="absolute tolerance on mm and mm/s "
                   "(adaptive solvers)")
    p.add_argument("--max-dt", type=float, default=4e-5, help="step of --solver verlet or "
                   "newmark, s")
    p.add_argument("--iterations", type=int, default=3, help="chord iterations per step of "
                   "--solver newmark")
    p.add_argument("--linearized", action="store_true", help="linearised strain measures")
    p.add_argument("--no-contact", action="store_true", help="switch the contact barrier off")
    p.add_argument("--float32", action="store_true", help="single precision")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")

    import design_engine  # noqa: F401  (x64, cache)
    from design_engine.design.design_io import save_design
    from design_engine.physics.geometry import InvalidDesignError
    from design_engine.solve.run import simulate_scene
    from design_engine.solve.simulate import SimulationError

    out = Path("runs") / args.preset if args.out is None else args.out
    try:
        scene = _build(args)
        config = _config(args)
        out.mkdir(parents=True, exist_ok=True)
        log.info("simulating %s: %d units, %d free DOFs, window %.1f ms (compiling on first use)",
                 scene.name, scene.n_units, scene.supports.free.size, scene.window)
        t0 = time.perf_counter()
        run = simulate_scene(scene, config)
    except (ValueError, InvalidDesignError, SimulationError, OSError) as exc:
        print(f"metarig simulate: error: {exc}", file=sys.stderr)
        return 2
    if args.task is not None:
        try:
            task = _task(args, *scene.lattice.shape, scene.design)
            run.metrics["task"] = task_summary(task, task.terms[0].scene, run.solution, config)
        except (ValueError, SimulationError) as exc:
            print(f"metarig simulate: error: {exc}", file=sys.stderr)
            return 2
    summary = {"scene": scene.name, "lattice": scene.lattice.describe(), "n_units": scene.n_units,
               "input_units": scene.input_units.tolist(),
               "precompression_strain": float(scene.loading.strain),
               "precompression": scene.loading.precompression if scene.loading.strain else None,
               "amplitude_m": float(scene.loading.amplitude) / 1e3,
               "frequency_hz": float(scene.loading.frequency) * 1e3,
               "material_si": scene.material.to_si(),
               "wall_s": time.perf_counter() - t0, **run.metrics}
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    ke = _block_ke_si(run)
    run.trajectory.save_npz(out / "trajectory.npz")
    save_design(out / "design.json", scene.lattice, scene.design)
    if not args.no_plots:
        _plots(out, scene, run, ke)
    for line in summary["solver"]["choice"]:
        log.info("solver: %s", line)
    log.info("target kinetic energy, mean over the window: %.6g J (%.6g mJ)",
             summary["target_ke_mean_J"], 1e3 * summary["target_ke_mean_J"])
    if "task" in summary:
        log.info("task %s: objective %.6g (%s)", summary["task"]["name"],
                 summary["task"]["objective"],
                 ", ".join(f"{k} {v:.6g}" for k, v in summary["task"]["objectives"].items()))
    log.info("wrote %s", ", ".join(sorted(f.name for f in out.iterdir())))
    return 0


def _block_ke_si(run) -> np.ndarray:
    from design_engine.solve.objectives import block_kinetic_energy

    return np.asarray(block_kinetic_energy(run.solution)) * 1e-3  # mJ -> J


def _plots(out: Path, scene, run, ke_j: np.ndarray) -> None:
    from design_engine.physics.regions import row_units
    from design_engine.solve.objectives import energy_components
    from design_engine.solve.plots import plot_energy_components, plot_ke_map, plot_line_peaks

    traj = run.trajectory
    k_peak = int(np.argmax(ke_j.sum(axis=1)))
    plot_ke_map(out / "ke_map.png", scene.reference_polygons_m(), traj.q[k_peak], ke_j.mean(axis=0),
                scene.targets, f"{scene.name}: time-averaged KE, lattice at t = "
                f"{traj.t[k_peak] * 1e3:.1f} ms (peak total KE)")
    s = run.metrics["solver"]
    comps = {k: v * 1e-3 for k, v in energy_components(scene, run.solution, s["linearized"],
                                                       s["use_contact"]).items()}
    first = next(iter(scene.targets.values()))
    plot_energy_components(out / "energy_components.png", traj.t, comps, ke_j[:, first].sum(axis=1),
                           f"{scene.name}: energy components")
    line = row_units(scene.lattice, scene.line_row)
    cols = scene.lattice.cell_of_block[line, 0] + (line % 2 if scene.lattice.kind == "kagome" else 0) * 0.5
    plot_line_peaks(out / "line_peak_ke.png", cols, ke_j[:, line].max(axis=0), scene.line_row,
                    f"{scene.name}: peak kinetic energy along row {scene.line_row}")


def modes_main(argv: list[str] | None = None) -> int:
    """Natural frequencies of a scene about its reference (or pre-compressed) state."""
    p = argparse.ArgumentParser(prog="metarig modes", description=modes_main.__doc__,
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    _scene_args(p)
    p.add_argument("--count", type=positive(int), default=20, help="lowest and highest modes to print")
    p.add_argument("--out", type=Path, default=None, help="folder for modes.json")
    args = p.parse_args(argv)
    import design_engine  # noqa: F401
    from design_engine.physics.geometry import InvalidDesignError
    from design_engine.physics.modal import modal_analysis
    from design_engine.solve.run import prestressed_state
    from design_engine.solve.simulate import SimulationError

    try:
        scene = _build(args)
        # stage scenes are analysed about their pre-compressed state (end of the ramp)
        modes = modal_analysis(scene, prestressed_state(scene))
    except (ValueError, InvalidDesignError, SimulationError, OSError) as exc:
        print(f"metarig modes: error: {exc}", file=sys.stderr)
        return 2
    f = modes.frequencies_hz
    n = min(args.count, f.size)
    print(f"{scene.name}: {f.size} free DOFs; lowest {n} modes [Hz]: "
          + ", ".join(f"{v:.2f}" for v in f[:n]))
    print(f"highest mode {f[-1]:.1f} Hz -> explicit-step bound ~ {2.8 / (2 * math.pi * f[-1]) * 1e3:.3f} ms")
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "modes.json").write_text(json.dumps({"scene": scene.name,
                                                         "frequencies_hz": f.tolist()}))
    return 0
