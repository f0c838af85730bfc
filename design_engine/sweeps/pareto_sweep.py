"""The Pareto sweep: scalarised design runs over weights x initial designs on Dask (spec 9.3).

Each run (weight w1, bias angle of the initial design) is one `metarig design` run with its own
folder `DIR/runs/w<w1>_start<deg>` (history, checkpoint, design files), executed on a Dask
worker; a run that was finished is skipped, a partial one resumes exactly (`optimize`), so a
re-run of the same command after a kill repeats nothing, and a worker that dies costs only the
evaluation in flight (Dask re-runs the task, which resumes from its checkpoint). Results reach
disk from the task that produced them; the scheduler holds no state that matters.

Outputs: `DIR/points.json` (every evaluation of every run: run, eval, weight, start, J1, J2 in
J, feasible), `DIR/front.json` (the non-dominated feasible points sorted by J1, each naming its
run and evaluation and pointing at a design file in `DIR/front/`), `DIR/pareto.png`, and
`DIR/sweep.json` (the settings; a re-run with other settings is refused).
"""

import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path


from metarig.readback import read_json, read_npz

log = logging.getLogger("metarig.pareto")

SWEEP_FORMAT = "metarig-pareto/1"
RESTORE_RUN = ("restore it from a copy to go on (the sweep's other files are left as they are), "
               "or start anew with another --out folder")


@dataclass(frozen=True)
class RunSpec:
    """One scalarised run: task source, weight w1, initial bias angle (deg), budget, size."""

    source: str
    w1: float
    start_deg: float
    max_evals: int | None
    size: tuple[int, int] | None

    @property
    def name(self) -> str:
        return f"w{self.w1:.3f}_start{self.start_deg:g}"


def _task(spec: RunSpec):
    from design_engine.design.task import load_task

    base = load_task(spec.source, size=spec.size)
    return load_task(spec.source, size=spec.size, max_evals=spec.max_evals,
                     bias_angle_deg=spec.start_deg, weights=base.pareto_weights(spec.w1))


def run_one(spec: RunSpec, out: str) -> dict:
    """Run (or finish, or skip) one scalarised design run; executed on a worker.

    Returns a small summary; everything that matters is in the run folder.
    """
    import design_engine  # noqa: F401  (x64, cache)
    from design_engine.design.optimize import resumable, run_design
    from design_engine.design.run_outputs import write_outputs

    folder = Path(out) / "runs" / spec.name
    task = _task(spec)
    run_path = folder / "run.json"
    if run_path.exists():
        run = read_json(run_path, "design-run record", RESTORE_RUN)
        if run.get("status") == "complete" and run.get("evaluations", 0) >= task.budget.max_evals:
            return {"run": spec.name, "evaluations": run["evaluations"], "skipped": True,
                    "compilations": 0}
    t0 = time.perf_counter()
    # one thread: the other workers fill the other cores
    res = run_design(task, folder, resume=resumable(folder), progress=False, threads=1)
    write_outputs(task, folder, res, plots=False)
    return {"run": spec.name, "evaluations": len(res.evaluations), "skipped": False,
            "compilations": res.compilations, "wall_s": time.perf_counter() - t0,
            "status": res.status}


def collect_points(out: Path, specs: list[RunSpec], term_names: tuple[str, str]) -> list[dict]:
    """Every recorded evaluation of every run as a point (J1, J2 in J, SI)."""
    points = []
    for spec in specs:
        path = out / "runs" / spec.name / "history.json"
        if not path.exists():
            continue
        hist = read_json(path, "design-run history", RESTORE_RUN)
        for e in hist.get("evaluations", []):
            obj = e["objectives"] or {}
            points.append({"run": spec.name, "eval": e["eval"], "weight": spec.w1,
                           "start_deg": spec.start_deg, "J1": obj.get(term_names[0]),
                           "J2": obj.get(term_names[1]),
                           "feasible": bool(e["feasible"] and not e["failed"])})
    return points


def write_results(out: Path, specs: list[RunSpec], task) -> dict:
    """points.json, front.json (+ the front's design files) and pareto.png from the run folders."""
    from design_engine.design.design_io import save_design
    from design_engine.sweeps.pareto import pareto_front, plot_pareto

    names = (task.terms[0].name, task.terms[1].name)
    points = collect_points(out, specs, names)
    front = pareto_front(points, task.senses)
    (out / "front").mkdir(exist_ok=True)
    for p in front:
        run_dir = out / "runs" / p["run"]
        xs = read_npz(run_dir / "checkpoint.npz", ("x",), "design-run checkpoint",
                      RESTORE_RUN)["x"]
        x = task.embed(xs[p["eval"] - 1])
        path = out / "front" / f"{p['run']}_eval{p['eval']}.json"
        save_design(path, task.lattice, x, name=f"{task.name} {p['run']} eval {p['eval']}",
                    task=task.name, objectives={names[0]: p["J1"], names[1]: p["J2"]},
                    eval=p["eval"])
        p["design"] = str(path.relative_to(out))
    doc = {"task": task.name, "terms": list(names), "senses": list(task.senses),
           "units": "J (mean target kinetic energy over the window)"}
    (out / "points.json").write_text(json.dumps({**doc, "points": points}, indent=1))
    (out / "front.json").write_text(json.dumps({**doc, "front": front}, indent=1))
    plot_pareto(out / "pareto.png", points, front, names,
                f"{task.name}: {len(points)} evaluated designs, {len(front)} on the front")
    return {"points": len(points), "front": len(front)}


PROGRESS_POLL_S = 5.0  # how often the sweep's bar re-counts the evaluations on disk


def evaluations_on_disk(out: Path, specs: list[RunSpec]) -> int:
    """Evaluations recorded so far by the runs of a sweep (their run.json files)."""
    n = 0
    for spec in specs:
        try:
            n += int(json.loads((out / "runs" / spec.name / "run.json").read_text())
                     .get("evaluations", 0))
        except (OSError, ValueError):
            pass
    return n


def run_sweep(source: str, out: Path, weights: list[float], starts: list[float], *,
              max_evals: int | None = None, size: tuple[int, int] | None = None,
              workers: int | None = None, scheduler: str | None = None,
              progress: bool = True) -> dict:
    """Run every (weight, start) design run of a two-objective task on Dask; write the front.

    Raises:
        TaskError: the task is not a two-objective task, or a weight lies outside [0, 1].
        ValueError: `out` holds a sweep with other settings, or a damaged sweep.json.
        ResumeError: a run's record in `out` is damaged (before any run starts).
    """
    from distributed import wait

    from design_engine.design.optimize import read_record, resumable
    from design_engine.sweeps.distributed import dask_client

    weights, starts = [float(w) for w in weights], [float(s) for s in starts]  # as sweep.json
    specs = [RunSpec(str(source), w, s, max_evals, size) for w in weights for s in starts]
    task = _task(specs[0])  # validates the task and the weights before any worker starts
    for spec in specs:
        task.pareto_weights(spec.w1)
    out.mkdir(parents=True, exist_ok=True)
    settings = {"format": SWEEP_FORMAT, "task": str(source), "weights": weights,
                "starts": starts, "max_evals": task.budget.max_evals,
                "size": list(task.lattice.shape)}
    sweep_path = out / "sweep.json"
    if sweep_path.exists():
        old = read_json(sweep_path, "sweep settings file", RESTORE_RUN)
        if {k: v for k, v in old.items() if k != "max_evals"} != \
                {k: v for k, v in settings.items() if k != "max_evals"}:
            raise ValueError(f"{out} holds a sweep with other settings ({sweep_path}); use "
                             "another --out")
    for spec in specs:  # a damaged run record is refused before any worker starts
        if resumable(out / "runs" / spec.name):
            read_record(out / "runs" / spec.name)
    sweep_path.write_text(json.dumps(settings, indent=1))
    bar = None
    total = len(specs) * task.budget.max_evals
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=total, initial=min(evaluations_on_disk(out, specs), total),
                   desc=f"pareto {task.name}", unit="eval", dynamic_ncols=True)
    done, t0, stopped = [], time.perf_counter(), False
    try:
        with dask_client(workers=workers, scheduler=scheduler) as client:
            log.info("%d runs (%d weights x %d starts) of up to %d evaluations; dashboard %s",
                     len(specs), len(weights), len(starts), task.budget.max_evals,
                     client.dashboard_link)
            runs = {client.submit(run_one, spec, str(out), key=f"run-{spec.name}-{out.name}",
                                  pure=False, retries=2): spec.name for spec in specs}
            pending = set(runs)
            while pending:
                try:
                    finished, pending = wait(pending, timeout=PROGRESS_POLL_S,
                                             return_when="FIRST_COMPLETED")
                except TimeoutError:
                    finished = set()
                for fut in finished:
                    try:
                        done.append(fut.result())
                    except Exception as exc:  # noqa: BLE001  one run's error: the others go on
                        why = f"{type(exc).__name__}: {exc}".splitlines()[0]
                        log.error("run %s failed: %s (its record so far is kept)", runs[fut], why)
                        done.append({"run": runs[fut], "failed": why})
                if bar is not None:  # evaluations as the runs' records on disk count them
                    bar.n = min(evaluations_on_disk(out, specs), total)
                    bar.set_postfix_str(f"{len(done)}/{len(specs)} runs done")
    except KeyboardInterrupt:  # Ctrl-C or SIGTERM; the local workers are stopped by now
        stopped = True
    if bar is not None:
        bar.close()
    counts = write_results(out, specs, task)
    if stopped:  # the front of what is on disk so far
        log.warning("stopped: %d evaluated designs so far, %d on the (partial) front",
                    counts["points"], counts["front"])
        raise KeyboardInterrupt
    return {"runs": done, "failed": [r for r in done if "failed" in r],
            "wall_s": time.perf_counter() - t0, **counts}
