"""Pareto sweeps on Dask: dominance, a sweep on a local cluster that loses a worker, resume."""

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from design_engine.commands.pareto import pareto_main
from design_engine.design.task import TaskError, load_task
from design_engine.sweeps.pareto import dominates, front_indices, pareto_front
from design_engine.sweeps.pareto_sweep import RunSpec, evaluations_on_disk, run_sweep

# 2 weights x 1 start x 2 evaluations: a run per worker of the test cluster, a killed run
# resumes between its evaluations, a killed or stopped one-worker command has a run left, and
# the front is that of 4 points (3 weights x 2 starts x 3 evaluations proved no more)
SWEEP = dict(weights=[0.0, 1.0], starts=[20.0], max_evals=2, size=(8, 6))
N_RUNS, N_EVALS = 2, 2
SPECS = [RunSpec("splitting", w, s, N_EVALS, (8, 6)) for w in SWEEP["weights"]
         for s in SWEEP["starts"]]


def _brute_force(points, senses):
    ok = [p for p in points if p["feasible"] and p["J1"] is not None]
    out = []
    for p in ok:
        if not any(dominates((q["J1"], q["J2"]), (p["J1"], p["J2"]), senses) for q in ok):
            if (p["J1"], p["J2"]) not in {(r["J1"], r["J2"]) for r in out}:
                out.append(p)
    return sorted(out, key=lambda p: p["J1"])


@pytest.mark.parametrize("senses", [("max", "max"), ("max", "min")])
def test_front_equals_a_brute_force_dominance_check(senses):
    rng = np.random.default_rng(7)
    v = np.round(rng.normal(size=(300, 2)), 1)  # rounding makes ties and duplicates
    idx = front_indices(v, senses)
    brute = [i for i in range(len(v))
             if not any(dominates(v[j], v[i], senses) for j in range(len(v)))]
    assert sorted(idx.tolist()) == sorted(brute)
    assert np.all(np.diff(v[idx, 0]) >= 0)
    assert dominates((2, 1), (1, 1), ("max", "max")) and not dominates((1, 1), (1, 1), senses)
    assert dominates((2, 0), (1, 1), ("max", "min"))


def test_pareto_weights_follow_the_spec_rules():
    assert load_task("splitting").pareto_weights(0.3) == (0.3, 0.7)
    fvp = load_task("focus-vs-protect")
    assert fvp.pareto_weights(0.75) == (0.75, -0.25) and fvp.senses == ("max", "min")
    with pytest.raises(TaskError):
        load_task("focusing").pareto_weights(0.5)
    with pytest.raises(TaskError):
        fvp.pareto_weights(1.5)


@pytest.fixture(scope="module")
def cluster():
    """A 2-worker local cluster (nannies restart killed workers), single-threaded workers."""
    from distributed import Client

    from design_engine.sweeps.distributed import local_cluster

    lc = local_cluster(2, dashboard_address=None)
    client = Client(lc)
    yield lc, client
    client.close()
    lc.close()


def _points(out: Path):
    return json.loads((out / "points.json").read_text())["points"]


@pytest.fixture(scope="module")
def straight(tmp_path_factory, cluster):
    """SWEEP run once without interruption on the test cluster: the reference of the resumes."""
    from design_engine.sweeps.pareto_sweep import run_one

    lc, client = cluster
    out = tmp_path_factory.mktemp("pareto") / "straight"
    # its first run alone on one worker: the other worker then loads the compiled programs from
    # the cache instead of compiling them at the same time (the sweep skips the finished run)
    first = next(iter(client.scheduler_info()["workers"]))
    client.submit(run_one, SPECS[0], str(out), workers=[first], pure=False).result()
    run_sweep("splitting", out, scheduler=lc.scheduler_address, progress=False, **SWEEP)
    return _points(out)


def test_a_sweep_survives_a_killed_worker_and_finds_the_front(tmp_path, cluster, straight):
    lc, client = cluster
    out = tmp_path / "sweep"
    result = {}

    def sweep():
        result["r"] = run_sweep("splitting", out, scheduler=lc.scheduler_address,
                                progress=True, **SWEEP)  # the bar polls the runs on disk

    th = threading.Thread(target=sweep)
    th.start()
    killed = None
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline and th.is_alive():
        started = list((out / "runs").glob("*/checkpoint.npz")) if (out / "runs").exists() else []
        if started:
            pids = client.run(os.getpid)
            killed = next(iter(pids.values()))
            os.kill(killed, signal.SIGKILL)
            break
        time.sleep(0.05)
    th.join(timeout=600)
    assert killed is not None and "r" in result
    assert len(result["r"]["runs"]) == N_RUNS
    points = _points(out)
    assert len(points) == N_RUNS * N_EVALS  # every run finished its budget despite the lost worker
    assert points == straight  # and the killed run resumed to the uninterrupted result
    assert evaluations_on_disk(out, SPECS) == len(points)  # what the progress bar counts
    for run in {p["run"] for p in points}:
        hist = json.loads((out / "runs" / run / "history.json").read_text())["evaluations"]
        assert [e["eval"] for e in hist] == list(range(1, N_EVALS + 1))
    front = json.loads((out / "front.json").read_text())["front"]
    brute = _brute_force(points, ("max", "max"))
    assert [(p["J1"], p["J2"]) for p in front] == [(p["J1"], p["J2"]) for p in brute]
    for p in front:
        assert (out / p["design"]).exists()
    assert (out / "pareto.png").stat().st_size > 0
    # a re-run repeats nothing and gives the same result
    again = run_sweep("splitting", out, scheduler=lc.scheduler_address, progress=False, **SWEEP)
    assert all(r["skipped"] for r in again["runs"]) and _points(out) == points
    # other settings in the same folder are refused
    with pytest.raises(ValueError):
        run_sweep("splitting", out, scheduler=lc.scheduler_address, progress=False,
                  **{**SWEEP, "starts": [25.0]})
    pareto_front(points, ("max", "max"))


def _foreign_record(folder: Path, checkpoint: bytes | None = None) -> None:
    """A readable design-run record of another task (or with the given checkpoint bytes)."""
    import io

    folder.mkdir(parents=True)
    (folder / "run.json").write_text(json.dumps({"format": "metarig-design-run/1",
                                                 "task": {"name": "other"}, "evaluations": 0}))
    (folder / "history.json").write_text(json.dumps({"evaluations": []}))
    if checkpoint is None:
        buf = io.BytesIO()
        np.savez(buf, x=np.zeros((0, 4)), f=np.zeros(0), grad=np.zeros((0, 4)))
        checkpoint = buf.getvalue()
    (folder / "checkpoint.npz").write_bytes(checkpoint)


def test_a_run_that_fails_leaves_the_others_to_finish(tmp_path, cluster):
    """One run's error (here a record of other task settings, which resume refuses) is reported
    with the run's name; the other runs finish, the front is written, and the command exits
    with 1."""
    lc, _ = cluster
    out = tmp_path / "sweep"
    _foreign_record(out / "runs" / "w0.000_start20")
    args = ["splitting", "--out", str(out), "--size", "8x6", "--weight-list", "0,1", "--starts",
            "20", "--max-evals", "2", "--quiet", "--scheduler", lc.scheduler_address]
    assert pareto_main(args) == 1
    res = run_sweep("splitting", out, weights=[0.0, 1.0], starts=[20.0], max_evals=2,
                    size=(8, 6), scheduler=lc.scheduler_address, progress=False)
    assert [r["run"] for r in res["failed"]] == ["w0.000_start20"]
    assert "other task settings" in res["failed"][0]["failed"]
    assert {p["run"] for p in _points(out)} == {"w1.000_start20"}
    assert len(_points(out)) == 2 and (out / "front.json").exists()


def _sweep_args(out: Path) -> list[str]:
    """`metarig pareto` arguments of SWEEP's settings (without the workers)."""
    return ["pareto", "splitting", "--out", str(out), "--size", "8x6", "--weight-list", "0,1",
            "--starts", "20", "--max-evals", str(N_EVALS), "--quiet"]


def _sweep_command(out: Path, until) -> subprocess.Popen:
    """Start `metarig pareto` (SWEEP's settings, its own local cluster of one worker, its own
    process group) and return once `until(run.json document)` holds for one of its runs (or
    after 300 s). One worker: each starts JAX and traces the programs again."""
    cmd = [sys.executable, "-m", "metarig", *_sweep_args(out), "--workers", "1"]
    with open(out.parent / f"{out.name}.stderr", "w") as err:  # a file: a pipe could fill
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=err,
                                start_new_session=True)
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline and proc.poll() is None:
        if any(until(json.loads(p.read_text())) for p in out.glob("runs/*/run.json")):
            break
        time.sleep(0.05)
    return proc


def test_a_killed_sweep_command_resumes_to_the_uninterrupted_result(tmp_path, cluster,
                                                                     straight):
    lc, _ = cluster
    out = tmp_path / "killed"
    proc = _sweep_command(out, lambda run: run.get("status") == "complete")
    os.killpg(proc.pid, signal.SIGKILL)  # the command, its scheduler and its workers
    proc.wait()
    assert not (out / "points.json").exists(), "the sweep was not killed in the middle"
    complete = {p.parent.name for p in out.glob("runs/*/run.json")
                if json.loads(p.read_text()).get("status") == "complete"}
    assert complete
    written = {n: (out / "runs" / n / "history.json").stat().st_mtime_ns for n in complete}
    # the same command again (on the test's cluster) continues the sweep
    assert pareto_main(_sweep_args(out)[1:] + ["--scheduler", lc.scheduler_address]) == 0
    assert {n: (out / "runs" / n / "history.json").stat().st_mtime_ns for n in complete} == \
        written  # finished runs were not repeated
    assert _points(out) == straight


def test_a_stopped_sweep_writes_the_front_of_what_it_has(tmp_path):
    """SIGTERM (a batch scheduler's stop, `kill`) stops the command like Ctrl-C: it exits with
    130 after writing points.json and front.json from every evaluation on disk."""
    out = tmp_path / "stopped"
    proc = _sweep_command(out, lambda run: run.get("evaluations", 0) >= 1)
    os.kill(proc.pid, signal.SIGTERM)  # the command only: it must stop its cluster itself
    try:
        proc.wait(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 130, (tmp_path / "stopped.stderr").read_text()[-2000:]
    points = _points(out)
    assert 1 <= len(points) == evaluations_on_disk(out, SPECS) < N_RUNS * N_EVALS
    front = json.loads((out / "front.json").read_text())["front"]
    assert [(p["J1"], p["J2"]) for p in front] == \
        [(p["J1"], p["J2"]) for p in _brute_force(points, ("max", "max"))]


def test_pareto_cli_refuses_bad_input_in_one_line(tmp_path, capsys):

    assert pareto_main(["focusing", "--out", str(tmp_path / "o"), "--weights", "3"]) == 2
    assert "two" in capsys.readouterr().err
    assert pareto_main(["splitting", "--out", str(tmp_path / "o"), "--weight-list", "0.5,2"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "[0, 1]" in err[0]
    # an empty --size was the task's size, silently; an empty --scheduler is no address
    assert pareto_main(["splitting", "--out", str(tmp_path / "o"), "--size", ""]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "size must look like 24x16, got ''" in err[0], err
    with pytest.raises(SystemExit) as e:
        pareto_main(["splitting", "--out", str(tmp_path / "o"), "--scheduler", ""])
    err = [line for line in capsys.readouterr().err.splitlines() if "error" in line]
    assert e.value.code == 2
    assert err == ["metarig pareto: error: argument --scheduler: --scheduler is empty"]
    assert not (tmp_path / "o").exists()


def test_a_damaged_sweep_record_is_refused_in_one_line_before_any_run(tmp_path, capsys):
    """A truncated checkpoint of one run, or a truncated sweep.json, ends the re-run at once in
    one line naming the file and what to do; no byte of the sweep folder changes."""
    import io

    out = tmp_path / "sweep"
    buf = io.BytesIO()
    np.savez(buf, x=np.zeros((2, 4)), f=np.zeros(2), grad=np.zeros((2, 4)))
    _foreign_record(out / "runs" / "w0.000_start20", checkpoint=buf.getvalue()[:300])
    args = ["splitting", "--out", str(out), "--size", "8x6", "--weight-list", "0,1", "--starts",
            "20", "--max-evals", "2", "--quiet", "--workers", "1"]

    def files():
        return {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}

    for damaged in ("runs/w0.000_start20/checkpoint.npz", "sweep.json"):
        if damaged == "sweep.json":
            (out / damaged).write_text('{"format": "metarig-pareto/1", "task": "spl')
        before = files()
        assert pareto_main(args) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "Traceback" not in err[0], err
        assert err[0].startswith(f"metarig pareto: error: {out / damaged}: damaged")
        assert "restore it from a copy" in err[0] and "another --out" in err[0]
        assert files() == before


def test_local_workers_start_with_the_worker_environment():
    """`dask_client(workers=N)`'s worker processes see every variable of `WORKER_ENV`, among
    them glibc's trim threshold (Dask's own default for its workers, which replacing the
    pre-spawn environment had dropped) and XLA on one thread, after this process's XLA_FLAGS
    (which the nanny had let win: the workers ran XLA on every core)."""
    from design_engine.sweeps.distributed import WORKER_ENV, dask_client

    assert WORKER_ENV["MALLOC_TRIM_THRESHOLD_"] == "65536"
    assert os.environ["XLA_FLAGS"]  # design_engine's, set in this process
    with dask_client(workers=1) as client:
        (seen,) = client.run(lambda: {k: os.environ.get(k) for k in WORKER_ENV}).values()
    flags = seen.pop("XLA_FLAGS")
    assert seen == {k: v for k, v in WORKER_ENV.items() if k != "XLA_FLAGS"}
    assert flags == f"{os.environ['XLA_FLAGS']} {WORKER_ENV['XLA_FLAGS']}"


def test_a_local_cluster_of_no_workers_is_refused_not_replaced_by_the_default():
    """`dask_client(workers=0)` (or fewer) raises before any process starts; only None means
    one worker per usable core."""
    from design_engine.sweeps.distributed import dask_client

    for workers in (0, -1):
        with pytest.raises(ValueError, match="need at least one worker"):
            with dask_client(workers=workers):
                pass


def _cores_of_every_thread() -> list[list[int]]:
    """In a worker: the cores each of its threads may run on."""
    return [sorted(os.sched_getaffinity(int(tid))) for tid in os.listdir("/proc/self/task")]


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="no CPU affinity here")
def test_local_workers_run_on_a_core_each(cluster):
    """Every thread of each local worker runs on one core, one the cores this process may use;
    two workers on two different ones where this process may use two or more."""
    _, client = cluster
    allowed = sorted(os.sched_getaffinity(0))
    seen = client.run(_cores_of_every_thread)
    cores = []
    for threads in seen.values():
        assert len(threads) >= 2 and all(t == threads[0] for t in threads)
        assert len(threads[0]) == 1 and threads[0][0] in allowed
        cores.append(threads[0][0])
    assert len(set(cores)) == min(2, len(allowed))


PIN = """
import json, os, sys, threading
from metarig.cores import pin_to_one_core
before = threading.Event()
threading.Thread(target=before.wait, daemon=True).start()  # a thread that exists already
core = pin_to_one_core(int(sys.argv[1]))
after = threading.Event()
threading.Thread(target=after.wait, daemon=True).start()  # one started afterwards
print(json.dumps([core, [sorted(os.sched_getaffinity(int(t)))
                         for t in os.listdir("/proc/self/task")]]))
"""


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="no CPU affinity here")
def test_a_pinned_process_runs_every_thread_on_one_core():
    """`pin_to_one_core(k)`: the k-th core this process may use, modulo their count, for the
    threads that exist and those started later."""
    allowed = sorted(os.sched_getaffinity(0))
    for index in (0, 1, 3):
        out = subprocess.run([sys.executable, "-c", PIN, str(index)], capture_output=True,
                             text=True, check=True)
        core, threads = json.loads(out.stdout)
        assert core == allowed[index % len(allowed)]
        assert len(threads) >= 3 and all(t == [core] for t in threads)


ONE_CORE_CLUSTER = """
import os
os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
from design_engine.sweeps.distributed import dask_client
with dask_client() as client:
    print(len(client.scheduler_info()["workers"]))
"""


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="no CPU affinity here")
def test_the_default_local_cluster_has_a_worker_per_core_this_process_may_use():
    """A process narrowed to one core (as `taskset -c K` does) gets one local worker, not one
    per core of the machine."""
    out = subprocess.run([sys.executable, "-c", ONE_CORE_CLUSTER], capture_output=True,
                         text=True, check=True, timeout=120)
    assert out.stdout.split()[-1] == "1"
