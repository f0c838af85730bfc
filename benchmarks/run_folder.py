"""The designs of a `metarig design` run folder, for the benchmarks that re-evaluate them."""

from pathlib import Path

import numpy as np


def run_designs(parser, task_name: str, run: Path, scene: str | None = None):
    """(task, designs [n_evaluations, n_free design]) of run folder `run` (its checkpoint.npz)
    of task `task_name`; `parser.error` (a one-line exit) when the folder holds no checkpoint or
    the task has no scene `scene`. `task.embed(designs[k - 1])` is evaluation k's design."""
    from design_engine.design.task import load_task

    if not (run / "checkpoint.npz").exists():
        parser.error(f"{run} holds no checkpoint.npz (a `metarig design` run folder)")
    task = load_task(task_name)
    if scene is not None and scene not in task.scenes:
        parser.error(f"task {task_name} has no scene {scene!r} (it has {sorted(task.scenes)})")
    return task, np.load(run / "checkpoint.npz")["x"]
