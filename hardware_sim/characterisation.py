"""Simulated material characterisation tests (spec 12.1, 12.2) from a given "true" material.

Hinge tests (12.1): the 4 x 6 rotating-squares sample (bias 20 deg), bottom row fixed, top row
displaced quasi-statically (tension v = +1.05 mm, compression v = -3.75 mm, shear u = +3.75 mm);
the engine's equilibrium (`design_engine.calibration.calibrate.make_hinge_forces`) gives the reaction
force, plus Gaussian load-cell noise. Written as Instron-style CSV files::

    metarig simulated Instron hinge test
    test=shear; sample=4x6 rotating squares, bias 20 deg; noise_N=0.02; seed=0
    Time (s),Extension (m),Load (N)
    0.000000e+00,0.000000e+00,1.234e-03
    ...

i.e. three header lines, then comma-separated rows time s, displacement magnitude m (the
crosshead travel; positive in every test), force N (positive in every test).

Free oscillation (12.2): two theta0 = 0 units joined by one ligament, one held, the other held
at an initial rotation and released at t = 0; the engine simulates the motion and the rotation
is sampled at 960 fps with Gaussian tracking noise. Written as a tracks `.npz` in the project's
trajectory format (`metarig.trajectory.Trajectory`: t [n] s from the release, q [n, 2, 3] with
unit 0 the held unit, unit 1 the free one; both carry the noise), plus the extra arrays
`test = "free-oscillation"`, `fps`, `free_unit = 1`.
"""

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from design_engine.calibration.hinge import (HINGE_HEADER, HINGE_TESTS, hinge_sample,
                                             make_hinge_forces)
from design_engine.calibration.oscillation import make_oscillation_model, oscillation_sample
from metarig.fields import param
from metarig.trajectory import Trajectory

# Noise levels. The paper states no load-cell noise; 0.02 N is ~0.5-1.5 % of the peak forces
# of the three tests (1.4-4.4 N) and matches a 10 N load cell at 0.2 % of full scale.
FORCE_NOISE_N = 0.02
# Rotation noise of a tracked 15 mm unit on the rig camera (6e-4 m/px, 1 % read noise): DIC
# sub-pixel error ~0.02 px over a ~12 px lever gives ~1.5e-3 rad; we use 1e-3 rad (1 sigma).
ROTATION_NOISE_RAD = 1e-3
POSITION_NOISE_M = 1.2e-5  # 0.02 px at 6e-4 m/px
FPS = 960.0


@dataclass(frozen=True)
class HingeTestConfig:
    """One simulated hinge-test run (an Instron-like ramp of one ligament test)."""

    test: str = param("tension", "which test", choices=tuple(HINGE_TESTS))
    max_displacement_m: float | None = param(None, "crosshead travel, m (None: the paper's "
                                             "1.05 / 3.75 / 3.75 mm)", 0.0, 0.05)
    n_points: int = param(200, "samples of the ramp, from 0 to the maximum", 2, 100000)
    rate_m_s: float = param(5e-3 / 60.0, "crosshead speed, m/s (5 mm/min; sets the time column "
                            "only: the test is quasi-static)", 0.0, 1.0)
    noise_n: float = param(FORCE_NOISE_N, "Gaussian force noise, N (1 sigma)", 0.0, 10.0)
    seed: int = param(0, "noise seed", 0, 2**31 - 1)


def hinge_curve(material, test: str, d_max_m: float, n_points: int, sample=None):
    """The noise-free test: (displacement m [n], force N [n]) for an engine `Material`.

    Evaluated as `fit_hinge` evaluates its model (the path from rest at d = 0 prepended, the
    forces with their Jacobian) so that both run one compiled program."""
    sample = sample or hinge_sample()
    d = np.linspace(0.0, d_max_m, n_points)
    k = np.asarray([float(material.k_stretch), float(material.k_shear), float(material.k_bend)])
    f, _ = make_hinge_forces(sample, test).with_jacobian(k, np.r_[0.0, d * 1e3])
    return d, np.asarray(f, np.float64)[1:]


def hinge_test(material, cfg: HingeTestConfig, sample=None, curve=None):
    """Simulate one run: (t s [n], displacement m [n], force N [n]) for an engine `Material`;
    `curve`: its `hinge_curve` when already computed (repeats differ by their noise only)."""
    d_max = cfg.max_displacement_m or HINGE_TESTS[cfg.test][2]
    d, f = curve or hinge_curve(material, cfg.test, d_max, cfg.n_points, sample)
    f = f + np.random.default_rng(cfg.seed).normal(0.0, cfg.noise_n, f.shape)
    return d / cfg.rate_m_s, d, f


def write_hinge_file(path, t_s, d_m, f_n, cfg: HingeTestConfig, nx: int = 4, ny: int = 6,
                     bias_deg: float = 20.0) -> Path:
    """Write an Instron-style file (module docstring)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    head = [h.format(test=cfg.test, nx=nx, ny=ny, bias=bias_deg, noise=cfg.noise_n, seed=cfg.seed)
            for h in HINGE_HEADER]
    rows = [f"{a:.6e},{b:.6e},{c:.6e}" for a, b, c in zip(t_s, d_m, f_n)]
    path.write_text("\n".join(head + rows) + "\n")
    return path


def hinge_tests(material, out_dir, tests=tuple(HINGE_TESTS), runs: int = 1, seed: int = 0,
                noise_n: float = FORCE_NOISE_N, n_points: int = 200) -> list[Path]:
    """All hinge tests (`runs` noisy repeats each) written to `out_dir/hinge_<test>_<run>.csv`."""
    sample = hinge_sample()
    paths = []
    for i, test in enumerate(tests):
        curve = hinge_curve(material, test, HINGE_TESTS[test][2], n_points, sample)
        for r in range(runs):
            cfg = HingeTestConfig(test, n_points=n_points, noise_n=noise_n,
                                  seed=seed + 1000 * i + r)
            t, d, f = hinge_test(material, cfg, sample, curve)
            paths.append(write_hinge_file(Path(out_dir) / f"hinge_{test}_{r}.csv", t, d, f, cfg))
    return paths


@dataclass(frozen=True)
class OscillationConfig:
    """The free-oscillation video: initial rotation, length, frame rate, tracking noise."""

    initial_rotation_rad: float = param(float(np.radians(10.0)), "initial rotation of the free "
                                        "unit, rad", -1.0, 1.0)
    n_frames: int = param(600, "frames of the video", 2, 10**6)
    fps: float = param(FPS, "frame rate, 1/s", 1.0, 1e6)
    noise_rad: float = param(ROTATION_NOISE_RAD, "tracking noise on rotations, rad (1 sigma)",
                             0.0, 1.0)
    noise_m: float = param(POSITION_NOISE_M, "tracking noise on positions, m (1 sigma)", 0.0,
                           0.01)
    seed: int = param(0, "noise seed", 0, 2**31 - 1)


def free_oscillation(material, cfg: OscillationConfig = OscillationConfig(), sample=None):
    """The tracked motion of the oscillation test for an engine `Material` (of the 2 x 1
    sample's lattice): a `Trajectory` (t from the release, noisy q, qdot by differences)."""
    sample = sample or oscillation_sample()
    t = np.arange(cfg.n_frames) / cfg.fps
    # the model is kept per sample and times (`make_oscillation_model`): repeats share it
    theta = np.asarray(make_oscillation_model(sample, t * 1e3)(material, cfg.initial_rotation_rad,
                                                                0.0))
    rng = np.random.default_rng(cfg.seed)
    q = np.zeros((t.size, 2, 3))
    q[:, 1, 2] = theta
    q[..., :2] += rng.normal(0.0, cfg.noise_m, q[..., :2].shape)
    q[..., 2] += rng.normal(0.0, cfg.noise_rad, q[..., 2].shape)
    return Trajectory.from_positions(t, q)


def write_oscillation(path, traj: Trajectory, cfg: OscillationConfig = OscillationConfig()) -> Path:
    """Save the tracks `.npz` (module docstring)."""
    return traj.save_npz(path, test=np.array("free-oscillation"), fps=np.array(cfg.fps),
                         free_unit=np.array(1))
