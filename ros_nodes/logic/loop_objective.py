"""The objective of a rig run for a closed loop: measured (from the tracked poses) and predicted
(the round's model on the measured input)."""

from pathlib import Path

import numpy as np


class ObjectiveError(RuntimeError):
    """The run cannot be read or compared, or its capture ends before the task's window."""


def objective_of_run(run_dir: Path, task, material: Path | None) -> tuple[dict, dict]:
    """The task's objective on a rig run: measured (the tracked poses' velocities) and predicted
    (the model, the run's nominal design with `material`, on the measured input), both through
    the comparison's differentiating filter of the frames (`comparison.metrics.frame_rates`),
    on the task's window and samples; and `predicted_full_band_J`, the model's objective from
    its own rates (what the design engine optimises): motion faster than the camera resolves
    is in it and not in the other two.

    The window is placed on the measured pulse onset as the task's scene places it on its
    pulse start; before the onset the sample is at rest (kinetic energy 0). Target units lost
    by the tracker are left out of both (and counted).

    Returns:
        (the `objective.json` document, arrays for the Rerun recording: t_s [n_t] since the
        onset, target_ke_measured_J / target_ke_predicted_J [n_t], polygons_m [n, nv, 2]).

    Raises:
        ObjectiveError: the run cannot be read or compared, or its capture ends before the window.
    """
    from design_engine.physics.material_file import MaterialFileError, with_material
    from ros_nodes.logic import comparison_run as run
    from ros_nodes.logic.comparison_run import CompareError
    from ros_nodes.logic.recording import RecordingError, read_recording
    from ros_nodes.recorded_run import measured_poses, recorded_design

    try:
        rec = read_recording(run_dir)
        scene, polygons = run.design_scene(recorded_design(rec, run_dir), where=str(rec.path))
        if material is not None:
            scene = with_material(scene, material)
        tracked = measured_poses(rec, "dic", polygons, None, 1, False)
        run.check_poses(scene, tracked.poses, where=str(rec.path))
        ec = run.simulate_and_compare(scene, tracked.poses, tracked.t0_s, rec.shaker_t_s,
                                      rec.shaker_u_m, rec.stage_t_s, rec.stage_closing_m,
                                      rec.closing_speed_m_s, rec.stage_hold_s,
                                      where=str(rec.path))
    except (RecordingError, CompareError, MaterialFileError) as exc:
        raise ObjectiveError(f"objective of {run_dir}: {exc}") from None
    c = ec.comparison
    task_scene = next(iter(task.scenes.values()))
    ld = task_scene.loading
    t_task = (task_scene.sample_times - ld.pulse_start - ld.delay) / 1e3  # s since the pulse
    if t_task[-1] > c.t[-1] + 1e-9:
        raise ObjectiveError(f"objective of {run_dir}: the capture ends {c.t[-1] * 1e3:.1f} ms after "
                        f"the pulse onset, before the task's window ({t_task[-1] * 1e3:.1f} ms); "
                        "give the rig a longer --record-s")
    from comparison.metrics import kinetic_energy

    keep = ec.measured.t >= c.metrics["onset_s"] - 1e-9  # the comparison's window
    ke_full = kinetic_energy(ec.simulated_abs.qdot[keep], scene.unit_masses_kg(),
                             scene.unit_inertias_kgm2())  # the engine's own rates, unfiltered
    terms, lost = {}, set()
    ke = {"measured": np.zeros_like(c.t), "predicted": np.zeros_like(c.t)}
    measured = predicted = full_band = 0.0
    for term in task.terms:
        ids = np.asarray(task.targets[term.target])
        used = ids[c.used[ids]]
        lost.update(int(i) for i in ids[~c.used[ids]])
        row = {"target": term.target, "weight": term.weight, "ids": [int(i) for i in ids],
               "units_tracked": int(used.size)}
        for side, field_ in (("measured", c.ke_exp), ("predicted", c.ke_sim)):
            series = field_[:, used].sum(axis=1)
            ke[side] += term.weight * series
            row[f"{side}_J"] = float(np.mean(np.interp(t_task, c.t, series, left=0.0)))
        row["predicted_full_band_J"] = float(np.mean(np.interp(
            t_task, c.t, ke_full[:, used].sum(axis=1), left=0.0)))
        terms[term.name] = row
        measured += term.weight * row["measured_J"]
        predicted += term.weight * row["predicted_J"]
        full_band += term.weight * row["predicted_full_band_J"]
    m = c.metrics
    doc = {
        "task": task.name, "goal": task.goal, "measured_J": measured, "predicted_J": predicted,
        "measured_over_predicted": measured / predicted if predicted else float("nan"),
        "predicted_full_band_J": full_band,
        "unit": "J (mean kinetic energy of the target over the task's window, weighted sum of "
                "the terms)",
        "terms": terms, "target_units_lost": sorted(lost),
        "window_s": [float(t_task[0]), float(t_task[-1])], "samples": int(t_task.size),
        "model_material": str(material) if material is not None else "default",
        "comparison": {k: m[k] for k in ("velocity_nrmse", "energy_map_correlation",
                                         "target_peak_ke_rel_err", "lost_units") if k in m},
        "onset_s": float(m["onset_s"]), "run": str(run_dir),
    }
    arrays = {"t_s": np.asarray(c.t, np.float64), "target_ke_measured_J": ke["measured"],
              "target_ke_predicted_J": ke["predicted"], "polygons_m": np.asarray(polygons)}
    return doc, arrays
