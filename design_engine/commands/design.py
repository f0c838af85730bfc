"""`metarig design`: optimise a design for a task preset or task file; outputs in a run folder.

Writes to --out: `design.json` (best feasible design, `metarig-design/1` with task, objectives,
max constraint, evaluation and provenance), `last_design.json`, `history.json` (every
evaluation), `checkpoint.npz` + `run.json` (resume), and the plots `history.png`,
`designs.png` (initial and optimised, coloured by time-averaged kinetic energy) and
`active_constraints.png`.
"""

import argparse
import logging
import sys
from pathlib import Path

from design_engine.design.run_outputs import write_outputs
from metarig.argtypes import grid_size, non_negative, positive

log = logging.getLogger("metarig.design")


def design_main(argv: list[str] | None = None) -> int:
    """Optimise a design by MMA for a task preset or a task file (TOML)."""
    from design_engine.design.task import preset_names

    p = argparse.ArgumentParser(prog="metarig design", description=design_main.__doc__,
                                epilog="presets: " + ", ".join(preset_names()))
    p.add_argument("task", nargs="?", help="task preset name or task file (.toml)")
    p.add_argument("--out", type=Path, help="run folder (default runs/design-<task>)")
    p.add_argument("--size", type=grid_size, help="lattice size NXxNY (default the task's)")
    p.add_argument("--max-evals", type=positive(int), help="objective evaluations, MMA inner "
                   "iterations included (default the task's)")
    p.add_argument("--max-time", type=positive(float), help="wall-time budget of the whole run, "
                   "s (default the task's)")
    p.add_argument("--max-solve-steps", type=positive(int), help="steps one adaptive solve of "
                   "an evaluation may take before the design counts as failed (default the "
                   "task's; presets: 20000)")
    p.add_argument("--bias-angle-deg", type=float, help="bias angle of the periodic initial "
                   "design, degrees")
    p.add_argument("--seed", type=non_negative(int), help="start from a random initial guess drawn with this "
                   "seed (periodic design + uniform noise, spec 3.1)")
    p.add_argument("--algorithm", choices=("mma", "nlopt-mma", "nlopt-ccsaq"),
                   help="optimiser (default the task's: mma)")
    p.add_argument("--material", type=Path, help="material file (TOML, metarig-material/1, SI) "
                   "for every scene of the task (default: the default material)")
    p.add_argument("--initial", type=Path, help="start from this design file (metarig-design/1, "
                   "the task's lattice) instead of the periodic design, e.g. to redesign a "
                   "tested design with a calibrated --material")
    p.add_argument("--threads", type=positive(int), help="solves that may run at once: the "
                   "task's scenes side by side, a half-step check beside its step (default: "
                   "the cores this process may use)")
    p.add_argument("--resume", action="store_true", help="continue the run in --out")
    p.add_argument("--list", action="store_true", help="list the task presets and exit")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    args = p.parse_args(argv)
    if args.list:
        from design_engine.design.task import load_task

        for name in preset_names():
            t = load_task(name)
            print(f"{name:<20}{t.description}")
        return 0
    if not args.task:
        p.error("a task preset or task file is required (see --list)")
    if args.initial is not None and (args.seed is not None or args.bias_angle_deg is not None):
        p.error("--initial gives the start; --seed and --bias-angle-deg make another one")
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    logging.getLogger("metarig").setLevel(logging.INFO)

    import design_engine  # noqa: F401  (x64, cache)
    from design_engine.design.constraints import constraint_count
    from design_engine.design.optimize import ResumeError, read_record, run_design
    from design_engine.design.task import TaskError, load_task
    from design_engine.physics.geometry import InvalidDesignError
    from design_engine.solve.simulate import SimulationError

    try:
        task = load_task(args.task, size=args.size, max_evals=args.max_evals,
                         max_time_s=args.max_time, max_solve_steps=args.max_solve_steps,
                         bias_angle_deg=args.bias_angle_deg,
                         seed=args.seed, algorithm=args.algorithm, material=args.material,
                         initial=args.initial)
        out = Path("runs") / f"design-{task.name}" if args.out is None else args.out
        if args.resume:
            read_record(out)  # a damaged record: one line, before anything else is said
        log.info("task %s (%s): %s lattice %dx%d, %d design variables, %d constraints, "
                 "%d scene(s), budget %d evaluations / %.0f s, optimiser %s",
                 task.name, task.source, task.lattice.kind, *task.lattice.shape, task.free.size,
                 constraint_count(task.lattice),
                 len(task.scenes), task.budget.max_evals, task.budget.max_time_s,
                 task.optimizer.algorithm)
        result = run_design(task, out, resume=args.resume, progress=not args.quiet,
                            threads=args.threads)
    except (TaskError, ResumeError, InvalidDesignError, SimulationError, OSError) as exc:
        print(f"metarig design: error: {exc}", file=sys.stderr)
        return 2
    write_outputs(task, out, result, plots=not args.no_plots)
    return 130 if result.status == "interrupted" else 0
