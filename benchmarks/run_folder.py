"""The designs of a `metarig design` run folder, for the benchmarks that re-evaluate them."""

from pathlib import Path

import numpy as np


def add_run_arguments(parser, scene: str, task: str = "focus-vs-protect") -> None:
    """`--task`, `--scene`, `--run` (required) and `--evals N ...` (required): the designs of a
    run folder a benchmark re-evaluates (`run_designs`)."""
    parser.add_argument("--task", default=task)
    parser.add_argument("--scene", default=scene)
    parser.add_argument("--run", type=Path, required=True, help="a `metarig design` run folder")
    parser.add_argument("--evals", nargs="+", type=int, required=True)


def run_designs(parser, task_name: str, run: Path, scene: str | None = None, evals=()):
    """(task, designs [n_evaluations, n_free design]) of run folder `run` (its checkpoint.npz)
    of task `task_name`; `parser.error` (a one-line exit) when the folder holds no checkpoint,
    the task has no scene `scene`, or the run no evaluation of `evals`.
    `task.embed(designs[k - 1])` is evaluation k's design."""
    from design_engine.design.task import load_task

    if not (run / "checkpoint.npz").exists():
        parser.error(f"{run} holds no checkpoint.npz (a `metarig design` run folder)")
    task = load_task(task_name)
    if scene is not None and scene not in task.scenes:
        parser.error(f"task {task_name} has no scene {scene!r} (it has {sorted(task.scenes)})")
    xs = np.load(run / "checkpoint.npz")["x"]
    bad = [e for e in evals if not 1 <= e <= len(xs)]
    if bad:
        parser.error(f"the run holds evaluations 1-{len(xs)}, not {bad}")
    return task, xs
