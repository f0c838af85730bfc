"""The machine a benchmark ran on, in words, for its results file (imported by the scripts here)."""

import os
import platform
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
