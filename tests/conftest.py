"""Shared test set-up: float64 JAX (via design_engine), the --runslow flag, an isolated DDS
domain per test process, and a compilation cache under the pytest cache.

Every test process (the session, or each xdist worker) picks its own `ROS_DOMAIN_ID` and sets
`ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST` before any rclpy context exists, so node processes that
tests start (they inherit the environment) never meet another test's nodes. The workers of one run
(pytest-xdist) take consecutive ids of one block, so two of them never share a domain.

Each xdist worker runs on a core of its own, with everything it starts (its tests compute on one
thread, and XLA otherwise forks its larger loops over every core: README, "Tests and
benchmarks").

Compiled XLA programs are kept in `.pytest_cache/jax` (unless `METARIG_JAX_CACHE` is set), all of
them (`METARIG_JAX_CACHE_MIN_S=0`), so the worker processes and the commands that tests start as
subprocesses reuse each other's programs.
"""

import json
import os
from pathlib import Path

_worker = int(os.environ.get("PYTEST_XDIST_WORKER", "gw0")[2:] or 0)
_workers = max(1, int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")))
# domains 1-100: the run picks a block of `_workers` consecutive ids, one per worker
os.environ["ROS_DOMAIN_ID"] = str(1 + _worker % _workers
                                  + _workers * (os.getppid() % max(1, 100 // _workers)))
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.setdefault("RCUTILS_LOGGING_BUFFERED_STREAM", "1")
os.environ.setdefault("METARIG_JAX_CACHE",
                      str(Path(__file__).resolve().parent.parent / ".pytest_cache" / "jax"))
# every program, even a single eager operation (~0.05 s to compile each, hundreds per test
# file): measured 1014 s -> 881 s for the cold suite on 2 cores, and a warm test file 40 -> 24 s
os.environ.setdefault("METARIG_JAX_CACHE_MIN_S", "0")

import pytest  # noqa: E402

import design_engine  # noqa: E402, F401  (enables x64 and the compilation cache)

if "PYTEST_XDIST_WORKER" in os.environ:
    # each worker process computes on one thread: on a core of its own, before its first XLA
    # computation (`metarig.cores`)
    from metarig.cores import pin_to_one_core

    pin_to_one_core(_worker)


@pytest.fixture
def emu():
    """Two Zaber stages (devices 1 and 2, axis 1) emulated on a pseudo-terminal."""
    from devices.stage.zaber_emulator import ZaberEmulator

    with ZaberEmulator() as e:
        yield e


def pytest_addoption(parser):
    parser.addoption("--runslow", action="store_true", default=False, help="also run slow tests")


# seconds each test file took in the last timed cold run (benchmarks/bench_suite.py --cold
# writes it): the suite hands out the longest files first
FILE_SECONDS = Path(__file__).resolve().parent / "file_seconds.json"


def longest_files_first(items: list) -> None:
    """Order `items` by their file's recorded time, longest first (files without a record
    after, in collection order; a file's tests keep their order). With `--dist loadfile
    --no-loadscope-reorder` (the Makefile's) the workers take files in this order, so no long
    file starts last while the other worker idles (cold suite on 2 cores: 328 s in collection
    order, 322 s this way)."""
    try:
        seconds = json.loads(FILE_SECONDS.read_text())
    except (OSError, ValueError):
        return
    first_seen = {}
    for item in items:
        first_seen.setdefault(item.nodeid.split("::")[0], len(first_seen))
    items.sort(key=lambda item: (-float(seconds.get(item.nodeid.split("::")[0], 0.0)),
                                 first_seen[item.nodeid.split("::")[0]]))


def pytest_collection_modifyitems(config, items):
    longest_files_first(items)
    if config.getoption("--runslow"):
        return
    skip = pytest.mark.skip(reason="slow: run with --runslow (make test-slow)")
    for item in items:
        if "slow" in item.keywords:
            item.add_marker(skip)
