"""pytest plugin for `bench_suite.py --compile-profile`: per test, the seconds JAX spent in the
test's own process tracing programs, lowering them and compiling them (XLA's backend), and how
many programs it compiled. Programs compiled in processes a test starts (commands, ROS nodes,
Dask workers) are not seen.

Each test process (the session, or each xdist worker) writes its rows to
`$METARIG_SUITE_PROFILE_DIR/rows_<worker>.json` when it finishes; `summarise` reads them back.
"""

import json
import os
import time
from collections import defaultdict
from pathlib import Path

import pytest

DIR_ENV = "METARIG_SUITE_PROFILE_DIR"
EVENTS = {"/jax/core/compile/backend_compile_duration": "compile_s",
          "/jax/core/compile/jaxpr_trace_duration": "trace_s",
          "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower_s"}

_seconds: dict[str, float] = defaultdict(float)
_count: dict[str, int] = defaultdict(int)
_rows: list[dict] = []


def _listen(event: str, duration: float, **_) -> None:
    key = EVENTS.get(event)
    if key is not None:
        _seconds[key] += duration
        _count[key] += 1


def pytest_configure(config):
    # here, not at import: `bench_suite.py` imports this module for `summarise` without JAX
    import jax.monitoring

    jax.monitoring.register_event_duration_secs_listener(_listen)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    _seconds.clear()
    _count.clear()
    start = time.perf_counter()
    yield
    _rows.append({"test": item.nodeid, "wall_s": time.perf_counter() - start,
                  **{k: _seconds.get(k, 0.0) for k in EVENTS.values()},
                  "programs": _count.get("compile_s", 0)})


def pytest_sessionfinish(session):
    folder = os.environ.get(DIR_ENV)
    if folder:
        worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
        (Path(folder) / f"rows_{worker}.json").write_text(json.dumps(_rows))


def summarise(folder: Path, top: int = 15) -> dict:
    """The rows in `folder`: totals, and per test file (longest first) and the `top` tests."""
    rows = [r for f in sorted(folder.glob("rows_*.json")) for r in json.loads(f.read_text())]
    keys = ("wall_s", *EVENTS.values())

    def total(rs):
        out = {k: round(sum(r[k] for r in rs), 1) for k in keys}
        out["programs"] = sum(r["programs"] for r in rs)
        return out

    files = defaultdict(list)
    for r in rows:
        files[r["test"].split("::")[0]].append(r)
    per_file = sorted(({"file": f, **total(rs)} for f, rs in files.items()),
                      key=lambda r: -r["wall_s"])
    tests = sorted(rows, key=lambda r: -r["wall_s"])[:top]
    return {"tests": len(rows), "total": total(rows), "files": per_file,
            "slowest": [{k: (round(v, 1) if isinstance(v, float) else v) for k, v in r.items()}
                        for r in tests]}
