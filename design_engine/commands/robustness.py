"""`metarig robustness`: the robustness map of a design (paper Fig. 2C), resumable, optionally on Dask.

    metarig robustness DESIGN --out DIR [--frequencies 20,25,...] [--amplitudes 0.1,0.2,...]
                       [--amplitude-unit s|mm|m] [--workers N | --scheduler ADDR]

R = J_target / J_rest over a grid of input frequencies (Hz) and amplitudes (by default in units
of the lattice spacing s: 0.5 is 7.5 mm for s = 15 mm); delay and window are tied to the lowest
frequency of the grid (see `design_engine.sweeps.robustness`). Writes to --out:
`robustness.json` (grid, R, target kinetic energy, solver configuration of every point, failed
points with their reasons, wall time, machine), rewritten after every finished chunk (status
"partial", then "complete"), and `robustness.png` (heat map). A re-run with the same --out reuses
every point already in robustness.json and computes only the rest.

With `--workers N` (N > 1) or `--scheduler ADDR` the remaining points are split into chunks and
mapped over Dask workers (`design_engine.sweeps.distributed.dask_client`); each worker compiles its
batch program once (the persistent JAX cache is shared).
"""

import argparse
import logging
import sys
from pathlib import Path

from design_engine.sweeps.robustness_map import AMPLITUDE_UNITS, MapError, MapRequest, run_map
from metarig.argtypes import number_list, positive, text

PROG = "metarig robustness"
DEFAULT_FREQUENCIES_HZ = tuple(20.0 + 5.0 * k for k in range(8))  # 20, 25, ..., 55 Hz
DEFAULT_AMPLITUDES_S = tuple(round(0.1 * k, 10) for k in range(1, 10))  # 0.1 ... 0.9 s


class _Parser(argparse.ArgumentParser):
    """argparse whose mistakes end in one stderr line (no usage block)."""

    def error(self, message):
        print(f"{PROG}: error: {message}", file=sys.stderr)
        raise SystemExit(2)


def _parser() -> argparse.ArgumentParser:
    from design_engine.sweeps.robustness import CPU_CHUNK, DEFAULT_CHUNK

    p = _Parser(prog=PROG, description=robustness_main.__doc__,
                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("design", type=Path, help="design file (JSON, metarig-design/1)")
    p.add_argument("--out", type=Path, required=True,
                   help="output folder (robustness.json, robustness.png); a re-run resumes")
    p.add_argument("--frequencies", type=number_list("frequencies", True, True),
                   default=DEFAULT_FREQUENCIES_HZ, help="input frequencies, Hz, comma list")
    p.add_argument("--amplitudes", type=number_list("amplitudes", True, True), default=DEFAULT_AMPLITUDES_S,
                   help="input amplitudes, comma list, in --amplitude-unit (default: units of the "
                   "lattice spacing s, so 0.5 is 7.5 mm for s = 15 mm); each below 2 s")
    p.add_argument("--amplitude-unit", choices=tuple(AMPLITUDE_UNITS), default="s",
                   help="unit of --amplitudes: s (lattice spacing), mm or m")
    p.add_argument("--scene", default="focusing-24x16",
                   help="scene preset, built on the design's lattice (its first target is the "
                   "target region)")
    p.add_argument("--chunk", type=positive(int), default=None,
                   help=f"grid points per vmap batch and at most per Dask task (default "
                   f"{DEFAULT_CHUNK} on an accelerator, {CPU_CHUNK} on the CPU, where larger "
                   "batches cost more per point)")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--workers", type=positive(int), default=None,
                       help="1 (default): in this process; N > 1: local Dask cluster of N workers")
    where.add_argument("--scheduler", type=text("--scheduler"),
                       help="address of a running Dask scheduler (tcp://HOST:PORT)")
    p.add_argument("--no-plot", action="store_true", help="skip robustness.png")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def robustness_main(argv: list[str] | None = None) -> int:
    """Robustness map R = J_target / J_rest of a design over input frequency and amplitude."""
    try:
        args = _parser().parse_args(argv)
    except SystemExit as exc:  # --help (0) or a parse error already reported in one line (2)
        return int(exc.code or 0)
    logging.basicConfig(level=logging.INFO, format="%(message)s")

    import design_engine  # noqa: F401  (x64, cache)
    from design_engine.physics.geometry import InvalidDesignError

    try:
        run_map(MapRequest(**vars(args)))
        return 0
    except (MapError, InvalidDesignError, ValueError, OSError) as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 2
