"""The steps of one comparison, shared by `metarig compare` (offline) and the comparison node
(live): the scene of a design, the refusals, the simulation, the summary, the run-folder files
and the messages' stamps. Pure: no ROS (`ros_nodes.convert.comparison_messages` turns a
comparison into messages).

Times on the rig clock, s; lengths m. Every refusal is a `CompareError` with one line.
"""

import json
from pathlib import Path

import numpy as np

SUMMARY_KEYS = ("velocity_nrmse", "energy_map_correlation", "target_peak_ke_rel_err",
                "max_displacement_error_m", "lost_units", "onset_s")
MIN_FRAMES = 3  # `comparison.experiment.compare_experiment` needs 3 frames or more
DIAGNOSTIC_NAME = "comparison"


class CompareError(ValueError):
    """Inputs that cannot be compared (one line for the user)."""


def _at(where: str, text: str) -> str:
    return f"{where}: {text}" if where else text


def design_scene(doc: dict, where: str = ""):
    """The nominal scene of a design document and its reference outlines [n, k, 2] (m).

    Raises:
        CompareError: no scene in the document, or outlines that are not the scene's.
    """
    from comparison.experiment import scene_of_design

    try:
        scene = scene_of_design(doc)
    except ValueError as exc:
        raise CompareError(_at(where, str(exc))) from None
    polygons = np.asarray(scene.reference_polygons_m())
    if "polygons_m" in doc and np.shape(doc["polygons_m"]) != polygons.shape:
        raise CompareError(_at(where, f"the design does not match the recording (its outlines "
                                      f"hold {len(doc['polygons_m'])} units, its scene "
                                      f"{scene.n_units})"))
    return scene, polygons


def check_poses(scene, poses, where: str = "", min_frames: int = MIN_FRAMES,
                lost_hint: str = "") -> None:
    """Refuse measured poses (a `Trajectory`) that cannot be compared with `scene`.

    Raises:
        CompareError: wrong unit count, fewer than `min_frames` frames, every unit lost.
    """
    if poses.n_units != scene.n_units:
        raise CompareError(_at(where, f"the poses hold {poses.n_units} units but the design "
                                      f"{scene.n_units}: the design does not match the "
                                      "recording"))
    need = max(int(min_frames), MIN_FRAMES)
    if poses.n_t < need:
        raise CompareError(_at(where, f"only {poses.n_t} frames; the comparison needs {need} "
                                      "or more"))
    if poses.lost is not None and poses.lost.all():
        raise CompareError(_at(where, "every unit was lost in every frame: nothing to compare"
                                      + lost_hint))


def simulate_and_compare(scene, poses, t0_s: float, shaker_t_s, shaker_u_m, stage_t_s,
                         stage_closing_m, closing_speed_m_s, stage_hold_s, where: str = ""):
    """`comparison.experiment.compare_experiment` with the rig's contact model.

    Raises:
        CompareError: the engine refused the inputs or did not finish.
    """
    from comparison.experiment import compare_experiment
    from design_engine.solve.policy import contact_config

    try:
        return compare_experiment(scene, poses, t0_s, shaker_t_s, shaker_u_m, stage_t_s,
                                  stage_closing_m, closing_speed_m_s, stage_hold_s,
                                  config=contact_config())
    except ValueError as exc:
        raise CompareError(_at(where, str(exc))) from None


def summary_of(ec, scene, poses_source: str, recording: str) -> dict:
    """The summary dict (`summary.json`, `/compare/summary`): the metrics (`SUMMARY_KEYS`
    first), then where the poses and the input came from, precompression (m), frames, scene."""
    m = ec.comparison.metrics
    summary = {k: m[k] for k in SUMMARY_KEYS}
    summary.update({k: v for k, v in m.items() if k not in summary})
    summary.update({
        "poses": poses_source, "input_source": ec.input.source,
        "precompression_m": ec.input.precompression_m, "frames": int(ec.measured.n_t),
        "scene": scene.name, "n_units": int(scene.n_units), "recording": str(recording),
    })
    sig = ec.measured.sigma
    if sig is not None and np.isfinite(sig).any():
        # how sure the tracking was (median stated standard error of the compared poses); the
        # metrics above are not weighted by it (`velocity_noise_nrmse` and
        # `velocity_nrmse_beyond_noise` say what of the velocity error its noise explains)
        summary["pose_sigma_median_m"] = float(np.nanmedian(np.hypot(sig[..., 0], sig[..., 1])))
        summary["pose_sigma_median_rad"] = float(np.nanmedian(sig[..., 2]))
        summary["weighted_by_pose_sigma"] = False
    return summary


def velocity_text(summary: dict) -> str:
    """'velocity NRMSE 1.81 %', with the part the tracking noise explains and the rest where the
    summary has them."""
    text = f"velocity NRMSE {summary['velocity_nrmse']:.2%}"
    if "velocity_nrmse_beyond_noise" in summary:
        text += (f" ({summary['velocity_noise_nrmse']:.2%} expected from tracking noise, "
                 f"{summary['velocity_nrmse_beyond_noise']:.2%} beyond it)")
    return text


def write_summary(out: Path, summary: dict) -> Path:
    """`out/summary.json`."""
    path = Path(out) / "summary.json"
    path.write_text(json.dumps(summary, indent=2))
    return path


def write_run_files(out: Path, scene, polygons: np.ndarray, poses, ec, frames=None,
                    calibration: dict | None = None) -> Path:
    """The comparison's files in `out`: the PNG plots, `tracks.npz` (the measured `poses`),
    `simulated.npz` and `comparison.rrd` (with the camera `frames` [n_f, H, W] at the frame
    times and their `calibration` when both are given). Returns the .rrd path."""
    from comparison.plots import window_samples, write_plots
    from comparison.rerun_log import write_rrd
    from design_engine.physics.regions import row_units

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    c = ec.comparison
    target = np.unique(np.concatenate([np.asarray(v) for v in scene.targets.values()]))
    row = row_units(scene.lattice, scene.line_row)
    # draw the measured motion on the simulated first-frame state (the tracker measures from it)
    q_exp = window_samples(c, ec.measured.t, ec.measured.q + ec.simulated_abs.q[0])
    q_sim = window_samples(c, ec.measured.t, ec.simulated_abs.q)
    write_plots(out, c, polygons, q_exp, q_sim, target, row, ec.measured.quality,
                ec.measured.lost, ec.measured.t - c.metrics["onset_s"])
    poses.save_npz(out / "tracks.npz")
    ec.simulated_abs.save_npz(out / "simulated.npz")
    rrd = out / "comparison.rrd"
    if frames is not None and calibration is not None:
        write_rrd(rrd, c, polygons, q_exp, q_sim, target,
                  frames=window_samples(c, ec.measured.t, frames),
                  m_per_px=calibration["m_per_px"], origin_px=tuple(calibration["origin_px"]),
                  y_up=bool(calibration.get("y_up", True)))
    else:
        write_rrd(rrd, c, polygons, q_exp, q_sim, target)
    return rrd


def frame_stamps_ns(ec) -> np.ndarray:
    """[n_t] rig-clock stamps of the compared frames, ns."""
    return np.round((ec.frame_t0_s + ec.measured.t) * 1e9).astype(np.int64)
