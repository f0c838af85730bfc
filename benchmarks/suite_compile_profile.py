"""pytest plugin for `bench_suite.py --compile-profile`: per test, the seconds JAX spent in the
test's own process tracing programs, lowering them and compiling them (XLA's backend), how
many programs it compiled and how many it read from the persistent compilation cache instead
(`cache_hits`), and the CPU seconds of the test (`cpu_s`: its process, plus the subprocesses it
started and waited for). Programs compiled in processes a test starts (commands, ROS nodes,
Dask workers) are not seen. Each compilation of at least PROGRAM_MIN_S seconds is also listed
(`compiled`: the program's name, the first 12 characters of its persistent-cache key, seconds),
so that `programs` can say which programs the suite compiled more than once, under one key
(the same program twice) or under several (one function traced with other shapes or
constants).

Each test process (the session, or each xdist worker) writes its rows to
`$METARIG_SUITE_PROFILE_DIR/rows_<worker>.json` when it finishes; `summarise` reads them back.
"""

import json
import logging
import os
import re
import resource
import threading
import time
from collections import defaultdict
from pathlib import Path

import pytest

DIR_ENV = "METARIG_SUITE_PROFILE_DIR"
EVENTS = {"/jax/core/compile/backend_compile_duration": "compile_s",
          "/jax/core/compile/jaxpr_trace_duration": "trace_s",
          "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower_s",
          "/jax/compilation_cache/cache_retrieval_time_sec": "cache_read_s"}

_seconds: dict[str, float] = defaultdict(float)
_count: dict[str, int] = defaultdict(int)
_rows: list[dict] = []
PROGRAM_MIN_S = 0.2
_compiled: list[list] = []
_missed: dict[int, tuple[str, str]] = {}  # thread -> (program, cache key) being compiled
_MISS = re.compile(r"CACHE MISS for '(.+)' with key '(.+)'")
_DONE = re.compile(r"Finished XLA compilation of (.+) in ([0-9.]+) sec")


class _Programs(logging.Handler):
    """Pairs JAX's debug record of a persistent-cache miss (name and key) with the record of
    that program's finished compilation, on the same thread."""

    def emit(self, record):
        msg = record.getMessage()
        thread = threading.get_ident()
        if m := _MISS.search(msg):
            _missed[thread] = (m.group(1), m.group(2))
        elif (m := _DONE.search(msg)) and float(m.group(2)) >= PROGRAM_MIN_S:
            name, key = _missed.pop(thread, (m.group(1), ""))
            _compiled.append([name, key.split("-")[-1][:12], round(float(m.group(2)), 2)])


def _listen(event: str, duration: float, **_) -> None:
    key = EVENTS.get(event)
    if key is not None:
        _seconds[key] += duration
        _count[key] += 1


def pytest_configure(config):
    # here, not at import: `bench_suite.py` imports this module for `summarise` without JAX
    import jax.monitoring

    jax.monitoring.register_event_duration_secs_listener(_listen)
    handler = _Programs(logging.DEBUG)
    for name in ("jax._src.compiler", "jax._src.interpreters.pxla", "jax._src.dispatch"):
        log = logging.getLogger(name)
        log.setLevel(logging.DEBUG)
        log.addHandler(handler)


def _cpu() -> float:
    own, children = (resource.getrusage(w) for w in (resource.RUSAGE_SELF,
                                                     resource.RUSAGE_CHILDREN))
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    _seconds.clear()
    _count.clear()
    _compiled.clear()
    start, cpu = time.perf_counter(), _cpu()
    yield
    _rows.append({"test": item.nodeid, "wall_s": time.perf_counter() - start,
                  "cpu_s": _cpu() - cpu,
                  **{k: _seconds.get(k, 0.0) for k in EVENTS.values()},
                  "programs": _count.get("compile_s", 0),
                  "cache_hits": _count.get("cache_read_s", 0),
                  "compiled": list(_compiled)})


def pytest_sessionfinish(session):
    folder = os.environ.get(DIR_ENV)
    if folder:
        worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
        (Path(folder) / f"rows_{worker}.json").write_text(json.dumps(_rows))


def all_rows(folder: Path) -> list[dict]:
    """Every test's row in `folder`, longest first, seconds rounded to 0.01."""
    rows = [r for f in sorted(folder.glob("rows_*.json")) for r in json.loads(f.read_text())]
    return [{k: (round(v, 2) if isinstance(v, float) else v) for k, v in r.items()}
            for r in sorted(rows, key=lambda r: -r["wall_s"])]


def summarise(folder: Path, top: int = 15) -> dict:
    """The rows in `folder`: totals, and per test file (longest first) and the `top` tests."""
    rows = all_rows(folder)
    keys = ("wall_s", "cpu_s", *EVENTS.values())

    def total(rs):
        out = {k: round(sum(r.get(k, 0.0) for r in rs), 1) for k in keys}
        for k in ("programs", "cache_hits"):
            out[k] = sum(r.get(k, 0) for r in rs)
        return out

    files = defaultdict(list)
    for r in rows:
        files[r["test"].split("::")[0]].append(r)
    per_file = sorted(({"file": f, **total(rs)} for f, rs in files.items()),
                      key=lambda r: -r["wall_s"])
    tests = sorted(rows, key=lambda r: -r["wall_s"])[:top]
    return {"tests": len(rows), "total": total(rows), "files": per_file,
            "slowest": [{k: (round(v, 1) if isinstance(v, float) and k != "compiled" else v)
                         for k, v in r.items() if k != "compiled"} for r in tests],
            "programs": programs(rows, top)}


def programs(rows: list[dict], top: int = 15) -> dict:
    """The compilations listed in `rows` (`compiled`) by program name: how often, under how many
    cache keys, their seconds, and the seconds of compilations that repeated a key compiled
    before in the suite (the same program compiled again, in a process whose cache did not
    have it yet); the `top` names by seconds, with the files that compiled them."""
    names: dict[str, dict] = {}
    seen: set[str] = set()
    repeated = 0.0
    for r in rows:
        for name, key, sec in r.get("compiled", []):
            n = names.setdefault(name, {"program": name, "compiles": 0, "keys": set(),
                                        "seconds": 0.0, "repeated_s": 0.0, "files": set()})
            n["compiles"] += 1
            n["seconds"] += sec
            n["files"].add(r["test"].split("::")[0])
            if key and key in seen:
                n["repeated_s"] += sec
                repeated += sec
            n["keys"].add(key)
            seen.add(key)
    table = sorted(names.values(), key=lambda n: -n["seconds"])
    return {"seconds": round(sum(n["seconds"] for n in table), 1),
            "repeated_key_s": round(repeated, 1),
            "names": len(table),
            "top": [{**n, "keys": len(n["keys"]), "seconds": round(n["seconds"], 1),
                     "repeated_s": round(n["repeated_s"], 1), "files": sorted(n["files"])}
                    for n in table[:top]]}
