"""The machine a benchmark ran on, in words, for its results file, and what the scripts here
share around it: their own compile cache, their report written (imported by the scripts here)."""

import json
import os
import platform
import shutil
from pathlib import Path


def cpu_model() -> str:
    """The CPU's model name (from /proc/cpuinfo; elsewhere what `platform` knows)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def describe() -> str:
    """'<cores> cores (<CPU model>)'."""
    return f"{os.cpu_count()} cores ({cpu_model()})"


def source_checkout() -> str:
    """The checkout whose `design_engine` this process imports (a benchmark run with
    `PYTHONPATH=DIR` times DIR's code): recorded as a results file's `source`."""
    import design_engine

    return str(Path(design_engine.__file__).resolve().parents[1])


def own_compile_cache(work: Path, warm: bool) -> None:
    """Point JAX's persistent compilation cache at `work`/jax-cache, emptied first unless
    `warm`, every program stored (set before `design_engine` is imported)."""
    cache = Path(work) / "jax-cache"
    if not warm:
        shutil.rmtree(cache, ignore_errors=True)
    os.environ["METARIG_JAX_CACHE"] = str(cache)
    os.environ["METARIG_JAX_CACHE_MIN_S"] = "0"


def write_report(out: Path, name: str, report: dict) -> Path:
    """`report` as `out`/`name`.json (the folder made); its path."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"{name}.json"
    path.write_text(json.dumps(report, indent=1) + "\n")
    return path
