"""Which cores this process may use, and how it keeps to one of them: the count that sizes every
pool of workers or threads (a design run's solves, a sweep's local workers, the tracker's
processes and threads), and the pinning of processes that each compute on one thread (a sweep's
local workers, the test suite's worker processes).

XLA's CPU runtime sizes its thread pool by the cores a process may use when its first
computation starts, and forks its larger loops over that pool, waking another core for each.
A process that computes on one thread anyway runs faster on one core: on the 2-core machine the
protection scene's fixed step took 76 us a step in two processes pinned to a core each against
115 us in two free to use both, and 77 against 96 us alone
(`benchmarks/bench_pinned_workers.py`, `benchmarks/results/bench_pinned_workers.json`).
"""

import os
from pathlib import Path


def usable_cores() -> int:
    """The cores this process may use: its CPU affinity, which `taskset`, a cgroup's cpuset or a
    container narrows, where `os.cpu_count()` counts every core of the machine (a pool sized by
    that doubles up processes on the cores they share)."""
    return len(os.sched_getaffinity(0))


def pin_to_one_core(index: int) -> int | None:
    """Confine this process, every thread of it and those it starts later, to one of the cores
    it may use: the `index`-th, modulo their count. Returns the core, or None where the system
    does not let a process choose its cores. Call it before the process's first XLA
    computation."""
    if not hasattr(os, "sched_setaffinity") or not Path("/proc/self/task").is_dir():
        return None
    allowed = sorted(os.sched_getaffinity(0))
    core = allowed[index % len(allowed)]
    for tid in os.listdir("/proc/self/task"):
        try:
            os.sched_setaffinity(int(tid), {core})
        except OSError:  # a thread that ended meanwhile
            pass
    return core
