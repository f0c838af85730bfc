"""Standard error of every registered pose (`pose_sigma`), calibrated against truth on
rendered sequences (pure, no ROS)."""

import numpy as np

from tracking.reference import RefSet

# `pose_sigma` against the true errors on rendered sequences, before this factor: RMS of
# error / sigma 1.18-1.22 (x, y, theta) on the default `metarig rig` footage (24x16 units of
# 16 px, 1 % read noise, blur), 1.0-1.5 on the synthetic scenes of tests/dic_synth.py (37 and
# 16 px units, 1 and 3 % noise); the reference frame's own noise, which the residual sees only
# once, is the main part left out
SIGMA_SCALE = 1.2
# share of the prefiltered noise's correlation area that the registration sees
# (`noise_correlation_factor`): with it, 95-99 % of the true errors lie within 2 sigma on the
# sharp synthetic scenes of tests/dic_synth.py without a floor (1 and 3 % noise)
NOISE_AREA_SHARE = 0.4
# The systematic part (`DICConfig.sigma_floor_px` 0.005 px, `sigma_blur_share` 0.006): with
# it, 96.6-97.6 % of the true errors lie within 2 sigma (x, y, theta) on the default
# `metarig rig` footage and 94.8-98.3 % on benchmarks/bench_dic_design.py's blurred optimised
# design (x 91 % without the blur share)


def pose_sigma(
    refs: RefSet, idx: np.ndarray, zncc: np.ndarray, prefilter_sigma_px: float = 0.0, floor_px=0.0
) -> np.ndarray:
    """Standard errors [k, 3] of the registered (wx px, wy px, alpha rad) of units `idx`.

    Two parts in quadrature. Noise: the Gauss-Newton covariance of a least-squares fit,
    sigma_I^2 (J^T J)^-1, with J the steepest-descent images of the reference subset
    (`RefSet.hinv` = (J^T J)^-1, intensity units) and sigma_I^2 the residual variance per
    subset point, read from the correlation (the normalised residual of ZNSSD sums to
    2 (1 - ZNCC), in intensity units times the reference's norm squared, over N - 3 degrees of
    freedom); a prefilter correlates the noise of neighbouring points, which the plain formula
    takes as independent (`noise_correlation_factor`). Systematic: a floor of `floor_px` (one
    value, or one per unit) on every subset point's position, over the subset's RMS radius for
    the rotation (`track_frame` gives `DICConfig.sigma_floor_px` and
    `DICConfig.sigma_blur_share` of the unit's motion since the previous frame, in quadrature). Scaled by `SIGMA_SCALE`, calibrated against truth
    on rendered sequences. A pose off by a wrong match is not covered (the checks flag those).
    """
    idx = np.asarray(idx)
    n = refs.count[idx].astype(np.float64)
    # (the correlation is summed in float32: a residual below its rounding reads as 1 - 1e-7)
    var_i = (
        2.0
        * np.clip(1.0 - np.asarray(zncc, np.float64), 1e-7, None)
        * refs.df[idx] ** 2
        / np.maximum(n - 3.0, 1.0)
    )
    diag = np.diagonal(refs.hinv[idx], axis1=1, axis2=2)
    noise2 = noise_correlation_factor(prefilter_sigma_px) ** 2 * var_i[:, None] * diag
    r2 = refs.r2[idx]
    floor2 = np.asarray(floor_px, np.float64)[..., None] ** 2 * np.stack(
        [np.ones_like(r2), np.ones_like(r2), 1.0 / np.maximum(r2, 1.0)], axis=-1
    )
    return SIGMA_SCALE * np.sqrt(noise2 + floor2)


def noise_correlation_factor(prefilter_sigma_px: float) -> float:
    """How much a Gaussian prefilter of `prefilter_sigma_px` widens the noise part of
    `pose_sigma`: sqrt(1 + NOISE_AREA_SHARE (A - 1)), A the correlation area of white noise
    after the filter, in pixels (sum of its normalised autocorrelation over the pixel grid);
    1 without a filter."""
    s = float(prefilter_sigma_px)
    if s <= 0:
        return 1.0
    i = np.arange(-int(np.ceil(6 * s)), int(np.ceil(6 * s)) + 1)
    area = float(np.exp(-(i**2) / (4.0 * s * s)).sum()) ** 2
    return float(np.sqrt(1.0 + NOISE_AREA_SHARE * (area - 1.0)))
