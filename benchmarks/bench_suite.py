"""The fast test suite as `make test` runs it: wall time, counts and the slowest tests, with the
machine and its load. Writes benchmarks/results/bench_suite.json (the README's "Tests" figures).

    .venv/bin/python benchmarks/bench_suite.py [--cold] [--compile-profile] [--env KEY=VALUE ...]
        [--out benchmarks/results/bench_suite.json] [-- extra pytest arguments]

`--cold` empties the suite's compilation cache (`.pytest_cache/jax`) first, as on a fresh clone
(CI); without it the cache of an earlier run is reused. A cold run of the whole suite (no extra
pytest arguments) that passes also writes each test file's seconds (set-up, call and tear-down
of its tests) to tests/file_seconds.json, from which tests/conftest.py hands out the longest
files first. The load average is read before and after the run: a figure taken beside other
work says so. The pytest arguments are those of the Makefile's `test` target (`PYTEST_ARGS`
there), so the figure is what a user gets. `cpu_s` is the CPU time (user + system) of the run's
processes, tests' subprocesses included.

`--compile-profile` also records, per test and test file, the seconds JAX spent in the test
processes themselves tracing, lowering and compiling programs, how many it compiled and how many
it read from the compilation cache, each compilation of 0.2 s or more by program (key
`programs`), and each test's CPU seconds (`suite_compile_profile.py`, a
pytest plugin; key `compile_profile`); every test's row goes to `<out>_tests.json` beside
`--out`, longest first. `--env KEY=VALUE` runs the suite with that variable set (recorded under
`env`), for trials such as `JAX_DISABLE_MOST_OPTIMIZATIONS=1`.
"""

import argparse
import json
import os
import platform
import re
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from machine import cpu_model

ROOT = Path(__file__).resolve().parent.parent
# the Makefile's `test` target: keep the two in step
MAKE_TEST_ARGS = ["-n", "auto", "--maxprocesses", "4", "--dist", "loadfile",
                  "--no-loadscope-reorder"]
FILE_SECONDS = ROOT / "tests" / "file_seconds.json"  # read by tests/conftest.py
SUMMARY = re.compile(r"^=*\s*(\d+ (?:passed|failed|error).*?) in ([\d.]+)s")
DURATION = re.compile(r"^([\d.]+)s (setup|call|teardown)\s+(\S+)")


def _counts(text: str) -> dict[str, int]:
    return {word: int(n) for n, word in re.findall(r"(\d+) (\w+)", text)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cold", action="store_true",
                        help="empty .pytest_cache/jax first (a fresh clone's first run)")
    parser.add_argument("--compile-profile", action="store_true",
                        help="also time JAX's tracing, lowering and compiling per test")
    parser.add_argument("--env", action="append", default=[], metavar="KEY=VALUE",
                        help="set this variable for the run (repeatable)")
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks/results/bench_suite.json")
    parser.add_argument("pytest_args", nargs="*", help="extra pytest arguments (after --)")
    args = parser.parse_args(argv)

    if args.cold:
        shutil.rmtree(ROOT / ".pytest_cache" / "jax", ignore_errors=True)
    cmd = [sys.executable, "-m", "pytest", *MAKE_TEST_ARGS, "-q", "--durations=0",
           "--durations-min=0", *args.pytest_args]
    env = dict(os.environ)
    extra_env = {}
    for item in args.env:
        key, sep, value = item.partition("=")
        if not sep or not key:
            parser.error(f"--env takes KEY=VALUE, got {item!r}")
        extra_env[key] = value
    env.update(extra_env)
    profile_dir = None
    if args.compile_profile:
        profile_dir = Path(tempfile.mkdtemp(prefix="metarig-suite-profile-"))
        cmd += ["-p", "suite_compile_profile"]
        env["PYTHONPATH"] = os.pathsep.join(filter(None, (str(ROOT / "benchmarks"),
                                                          env.get("PYTHONPATH"))))
        from suite_compile_profile import DIR_ENV
        env[DIR_ENV] = str(profile_dir)
    load_before = os.getloadavg()
    cpu_before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, env=env)
    lines = []
    assert proc.stdout is not None
    for line in proc.stdout:  # show the run as it goes
        sys.stdout.write(line)
        lines.append(line.rstrip("\n"))
    rc = proc.wait()
    wall = time.perf_counter() - t0
    cpu_after = resource.getrusage(resource.RUSAGE_CHILDREN)
    load_after = os.getloadavg()

    summary = next((m for m in map(SUMMARY.search, reversed(lines)) if m), None)
    # every test phase, longest first (pytest sorts them)
    durations = [{"seconds": float(m[1]), "phase": m[2], "test": m[3]}
                 for m in map(DURATION.match, lines) if m]
    result = {
        "command": " ".join(["python -m pytest", *MAKE_TEST_ARGS, *args.pytest_args]),
        "cold_cache": args.cold,
        **({"env": extra_env} if extra_env else {}),
        "exit_code": rc,
        "wall_s": round(wall, 1),
        "pytest_s": float(summary[2]) if summary else None,
        "cpu_s": round(cpu_after.ru_utime + cpu_after.ru_stime
                       - cpu_before.ru_utime - cpu_before.ru_stime, 1),
        "counts": _counts(summary[1]) if summary else {},
        "slowest": durations[:10],
        "machine": {"cpu": cpu_model(), "cores": os.cpu_count(),
                    "python": platform.python_version()},
        "load_average_1min": {"before": round(load_before[0], 2),
                              "after": round(load_after[0], 2)},
        "date": time.strftime("%Y-%m-%d %H:%M", time.gmtime()) + " UTC",
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    if profile_dir is not None:
        from suite_compile_profile import all_rows, summarise
        result["compile_profile"] = summarise(profile_dir)
        rows_out = args.out.with_name(args.out.stem + "_tests.json")
        rows_out.write_text(json.dumps(all_rows(profile_dir), indent=0) + "\n")
        shutil.rmtree(profile_dir, ignore_errors=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    if args.cold and rc == 0 and durations and not args.pytest_args:
        per_file: dict[str, float] = {}
        for row in durations:
            name = row["test"].split("::")[0]
            per_file[name] = per_file.get(name, 0.0) + row["seconds"]
        FILE_SECONDS.write_text(json.dumps(
            {k: round(v, 1) for k, v in sorted(per_file.items(), key=lambda kv: -kv[1])},
            indent=1) + "\n")
        print(f"-> {FILE_SECONDS}: {len(per_file)} files")
    print(f"-> {args.out}: {result['wall_s']} s wall, {result['counts']}, exit code {rc}")
    return rc


if __name__ == "__main__":
    try:
        sys.exit(main())
    except KeyboardInterrupt:
        sys.exit(130)
