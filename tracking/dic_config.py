"""Settings of the DIC tracker (`DICConfig`) and their fit to small units (pure, no ROS)."""

from dataclasses import dataclass, replace

import numpy as np

from metarig.fields import param
from metarig.polygon import signed_areas


@dataclass(frozen=True, slots=True)
class DICConfig:
    """Tracker settings (each field's description, unit and bounds in its metadata).

    Notes on the fields whose meaning needs more than a line:
        acquire_radius_px: 0 takes a tenth of the sample's height in the image, which covers
            any pre-compression the rig allows (9 %), even from one stage alone.
        verify_px, verify_rad: a pose registered against a refreshed reference must agree this
            well with the reference image's own subset where that registers poorly, else the
            unit is lost (`tracking.dic.track_frame`).
        check_sigmas, check_floor_px, check_max_px: a piece (`check_pieces`,
            `tracking.checks`) whose centroid lands further from where the unit's pose puts it
            than check_sigmas of its standard error (at the unit's correlation), bounded to
            [check_floor_px, check_max_px], fails the pose: the unit is searched again from its
            pieces' motion, and lost if that fails too. The upper bound keeps a poor fit from
            excusing itself: a wrong pose correlates worse, which widens every standard error;
            0.25 px at a piece is ~30 mrad on a sliver whose pieces lie 9 px from its centre. A
            piece too small for it (check_sigmas of its standard error at a near-perfect fit
            beyond it) is bounded by that instead.
        neighbour_px, neighbour_static_px: the check of every pose against its bonded
            neighbours (`tracking.neighbours`, where the tracker knows the lattice's ligaments):
            a ligament whose end-to-end vector departs more than neighbour_static_px from its
            rest vector turned by its units' mean rotation, or accelerates by more than
            neighbour_px in a frame (second difference over three frames, both units tracked
            in all three), fails; a unit whose ligaments fail to more than half of its tracked
            bonded neighbours is searched again from its neighbours' motion and lost if that
            fails the check too. Set from the exact truth of the optimised 24x16 focusing
            design under its 7.5 mm pulse at 1000 fps (benchmarks/bench_dic_design.py): at
            most 7.6 px and 2.0 px there (99.9 %: 4.0 and 0.77 px), so the bounds flag gross
            errors (a match on a neighbour's or a self-similar texture), not fine ones (the
            pieces' check's job). The acceleration bound holds between a camera's consecutive
            frames, not between frames far apart (the live preview's: `ros_nodes.dic_params`
            leaves it out).
        sigma_floor_px, sigma_blur_share: the systematic part of each pose's standard error
            (`tracking.pose_sigma`), in quadrature with the noise part. Both defaults are
            measured on the simulated rig's footage (exposure half a frame); on a real camera,
            measure them with rigid-motion tests (a blur share of 0 where the exposure is
            short).
    """

    margin_px: float = param(
        2.5, "subset points keep this distance from the unit outline, px", 0.0, 50.0
    )
    min_points: int = param(
        50, "units with fewer subset points are never tracked (always lost)", 4, 100000
    )
    max_iter: int = param(20, "IC-GN iteration cap per frame", 1, 1000)
    tol_px: float = param(
        2e-3, "IC-GN convergence: estimated remaining error of any subset point, px", 1e-6, 1.0
    )
    max_move_px: float = param(
        8.0, "IC-GN gives up when the pose wanders this far from its start, px", 0.1, 1000.0
    )
    zncc_lost: float = param(
        0.8, "a tracked unit whose ZNCC stays below this is declared lost", 0.0, 1.0
    )
    zncc_reacquire: float = param(
        0.9, "below this a search is tried; a lost unit must reach it again", 0.0, 1.0
    )
    zncc_update: float = param(0.9, "a unit tracked below this gets a new reference", 0.0, 1.0)
    max_ref_rotation: float = param(
        0.2, "a unit rotated more than this from its reference gets a new one, rad", 0.0, 3.2
    )
    search_radius_px: int = param(
        12, "half-width of the re-acquisition window around the prediction, px", 1, 1000
    )
    lost_search_radius_px: int = param(
        24, "the same for units already lost (around their last pose), px", 1, 2000
    )
    prefilter_sigma_px: float = param(
        0.8, "Gaussian smoothing of every frame before tracking, px (0: none)", 0.0, 10.0
    )
    predict: bool = param(
        True, "warm-start from a constant-velocity prediction (else the last pose)"
    )
    acquire_radius_px: int = param(
        0,
        "half-width of the first frame's search for every unit "
        "around its reference position, px (0: auto)",
        0,
        10000,
    )
    acquire_max_rotation: float = param(
        0.7, "largest trial rotation of the first frame's search, rad", 0.0, 3.2
    )
    acquire_rotation_step: float = param(
        0.05, "step between the first frame's trial rotations, rad", 1e-3, 1.0
    )
    acquire_neighbours: int = param(
        4,
        "units without a search template (slender ones) start "
        "from the rigid motion of this many nearest found units",
        1,
        64,
    )
    verify_px: float = param(
        0.5,
        "a pose from a refreshed reference must agree this well "
        "with the reference image's (largest subset-point shift), px",
        0.0,
        100.0,
    )
    verify_rad: float = param(0.01, "the same for the rotation, rad", 0.0, 3.2)
    check_pieces: int = param(
        2,
        "pieces each unit's subset is cut into along its long axis to "
        "check every pose (0: no check; not 1)",
        0,
        16,
    )
    check_sigmas: float = param(
        5.0,
        "a piece further than this many standard errors from where the pose puts it fails the pose",
        0.0,
        100.0,
    )
    check_floor_px: float = param(0.1, "smallest bound of the pieces' check, px", 0.0, 10.0)
    check_max_px: float = param(
        0.25, "largest bound of the pieces' check at a poor fit, px", 0.0, 10.0
    )
    neighbour_px: float = param(
        3.0,
        "largest acceleration of a ligament's end-to-end vector in a frame, px "
        "(0: no check against the neighbours)",
        0.0,
        1000.0,
    )
    neighbour_static_px: float = param(
        10.0,
        "largest departure of a ligament's end-to-end vector from its rest vector turned "
        "by its units' mean rotation, px",
        0.0,
        1000.0,
    )
    sigma_floor_px: float = param(
        0.005,
        "systematic error of every subset point's registered "
        "position that noise does not explain, px",
        0.0,
        10.0,
    )
    sigma_blur_share: float = param(
        0.006,
        "unmodelled motion blur: the systematic floor grows "
        "by this share of the unit's motion since the previous "
        "frame",
        0.0,
        1.0,
    )

    def __post_init__(self):
        if not (0.0 <= self.zncc_lost <= self.zncc_reacquire <= 1.0):
            raise ValueError("need 0 <= zncc_lost <= zncc_reacquire <= 1")
        if self.margin_px < 0 or self.max_iter < 1 or self.tol_px <= 0:
            raise ValueError("margin_px >= 0, max_iter >= 1 and tol_px > 0 are required")
        if self.check_pieces == 1 or self.check_pieces < 0:
            raise ValueError(f"check_pieces must be 0 (no check) or >= 2, got {self.check_pieces}")


# outline margin of designs whose smallest unit needs a thinner one (`settings_for_units`). A
# sliver's rotation is measured by the few pixel rows along its length, and a margin of 1.5 px
# took most of them: on the optimised 24x16 focusing design (benchmarks/bench_dic_design.py,
# pixels integrated at 4 x 4 samples) the rotation p99 is 3.22 mrad at 1.5 px, 2.82 at 1.0 and
# 2.49 at 0.5. Kept at 1.0: the outline's own edge moves the pose more the closer the subset
# comes (noise-free renders: p99 0.93, 1.69 and 2.20 mrad), and a cut edge is rougher than a
# rendered one
SMALL_UNIT_MARGIN_PX = 1.0
SMALL_UNIT_MIN_POINTS = 16


def settings_for_units(
    polygons_m: np.ndarray, m_per_px: float, cfg: DICConfig | None = None
) -> DICConfig:
    """`cfg` (default settings when None), with a thinner outline margin and a smaller subset
    floor when the smallest unit would otherwise hold fewer than `min_points` subset pixels
    (area minus a `margin_px` band along the perimeter, in px^2): small or slender units in a
    modest image are then tracked instead of lost."""
    cfg = cfg or DICConfig()
    p = np.asarray(polygons_m, np.float64) / m_per_px
    area = np.abs(signed_areas(p))
    perimeter = np.linalg.norm(p - np.roll(p, -1, axis=-2), axis=-1).sum(axis=-1)
    if np.min(area - perimeter * cfg.margin_px) >= cfg.min_points:
        return cfg
    return replace(
        cfg,
        margin_px=min(cfg.margin_px, SMALL_UNIT_MARGIN_PX),
        min_points=min(cfg.min_points, SMALL_UNIT_MIN_POINTS),
    )
