"""A small sample for the imperfect specimen's tests (and `benchmarks/bench_discrepancy.py`).

The 8x6 focusing lattice (the size the comparison and calibration tests compile) with a fixed
asymmetric design: the periodic lattice is mirror symmetric and its response under a pulse on
the mid rows sits on a bifurcation (an imperfection of 1e-4 in the stiffnesses already moves
its velocities by 4 %, 1e-3 by 37 %), so that it would measure the tipping, not the size of an
imperfection.
"""

import math
from pathlib import Path

import numpy as np


def asymmetric_design(path: Path) -> Path:
    """The 8x6 periodic design (25 deg) with every design coordinate moved by N(0, 0.5 mm),
    seed 7, written to `path` (a design file); returns the path."""
    import design_engine as de
    from design_engine.design.design_io import save_design
    from design_engine.physics.lattice import periodic_design

    lat = de.build_scene("focusing-24x16", nx=8, ny=6).lattice
    x = np.asarray(periodic_design(lat, math.radians(25.0)))
    return save_design(path, lat, x + np.random.default_rng(7).normal(0.0, 0.5, x.size))


def raised_cosine(amplitude_m: float, t_end_s: float):
    """The paper's pulse shape (peak `amplitude_m`, 30 Hz) starting 5 ms in, on 0.1 ms samples:
    (t [n] s, u [n] m)."""
    t = np.arange(0.0, t_end_s, 1e-4)
    return t, 0.5 * amplitude_m * (1 - np.cos(2 * np.pi * 30 * np.clip(t - 0.005, 0, 1 / 30)))
