"""Dask distributed for the sweeps (the one owner of dask): a client on a local or remote cluster.

`dask_client(workers=N)` starts a `LocalCluster` of N single-threaded worker processes (default
one per core) with the scheduler, the workers and the dashboard on 127.0.0.1 only;
`dask_client(scheduler="tcp://HOST:PORT")` connects to an existing cluster instead (workers
started by `dask worker`, `dask-jobqueue` on SLURM/PBS, ...: they must reach the same files).
Workers are spawned with one thread for XLA and BLAS each (a sweep's parallelism is its
tasks), and share the persistent compilation cache, so a scene's program is compiled once per
cache, not once per task. A local cluster's worker N runs on core N, modulo the cores this
process may use (`OneCorePerWorker`, `metarig.cores.pin_to_one_core`: XLA otherwise forks its larger
loops over every core and wakes the other core for each).
"""

import contextlib
import logging
import os

from distributed.diagnostics.plugin import WorkerPlugin

from metarig.cores import pin_to_one_core, usable_cores

log = logging.getLogger("metarig.distributed")

WORKER_ENV = {
    "OMP_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "XLA_FLAGS": "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1",
    "EQX_ON_ERROR": "nan",
    # glibc hands freed memory back to the system (Dask's own default for its workers, which
    # replacing its pre-spawn environment dropped: a focus-vs-protect front's workers then grew
    # to 10-11 GB and Dask paused them)
    "MALLOC_TRIM_THRESHOLD_": "65536",
}


def worker_environment() -> dict[str, str]:
    """Environment variables every worker process starts with."""
    env = dict(WORKER_ENV)
    cache = os.environ.get("METARIG_JAX_CACHE")
    if cache is not None:
        env["METARIG_JAX_CACHE"] = cache
    return env


def worker_xla_flags() -> str:
    """A local worker's XLA_FLAGS: this process's (`design_engine` sets its code generators),
    then WORKER_ENV's."""
    return " ".join(filter(None, (os.environ.get("XLA_FLAGS", ""), WORKER_ENV["XLA_FLAGS"])))


class OneCorePerWorker(WorkerPlugin):
    """Runs a local cluster's worker (named by its number) on one core of its own
    (`pin_to_one_core`); a worker with another name is left as it is."""

    def setup(self, worker) -> None:
        try:
            index = int(worker.name)
        except (TypeError, ValueError):
            return
        core = pin_to_one_core(index)
        if core is not None:
            log.debug("worker %s runs on core %d", worker.name, core)


def local_cluster(n: int, dashboard_address: str | None = "127.0.0.1:0"):
    """A `LocalCluster` of `n` single-threaded worker processes on 127.0.0.1 that start with
    `worker_environment()`. Dask's nanny lets a variable of its own process win over its
    pre-spawn environment, and this process has XLA_FLAGS set (`design_engine` sets its code
    generators), so the workers' XLA_FLAGS (this process's, then one thread for XLA) go to the
    nanny as the worker's own environment, set before the worker starts XLA. Each worker runs
    on one core (`OneCorePerWorker`), a killed one restarted by its nanny on the same."""
    import dask
    from distributed import LocalCluster

    with dask.config.set({"distributed.nanny.pre-spawn-environ": worker_environment()}):
        return LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                            host="127.0.0.1", dashboard_address=dashboard_address,
                            silence_logs=logging.WARNING, env={"XLA_FLAGS": worker_xla_flags()},
                            plugins={OneCorePerWorker()})


@contextlib.contextmanager
def dask_client(workers: int | None = None, scheduler: str | None = None):
    """A `distributed.Client` for the sweep; the local cluster (if any) is closed on exit.

    Args:
        workers: worker processes of a new LocalCluster (default: one per core this process
            may use, so that each runs on a core of its own).
        scheduler: address of an existing scheduler (`tcp://HOST:PORT`); excludes `workers`.
    """
    from distributed import Client

    logging.getLogger("distributed").setLevel(logging.WARNING)

    if scheduler is not None and workers is not None:
        raise ValueError("give either a worker count or a scheduler address, not both")
    if scheduler is not None:
        client = Client(scheduler, timeout="30s")
        try:
            log.info("connected to %s (%d workers); dashboard %s", scheduler,
                     len(client.scheduler_info().get("workers", {})), client.dashboard_link)
            yield client
        finally:
            client.close()
        return
    n = usable_cores() if workers is None else workers
    if n < 1:
        raise ValueError(f"need at least one worker, got {n}")
    cluster = local_cluster(n)
    client = Client(cluster)
    try:
        log.info("local Dask cluster: %d single-threaded workers; dashboard %s", n,
                 client.dashboard_link)
        yield client
    finally:
        client.close()
        cluster.close()
