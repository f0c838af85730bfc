"""Experiment against simulation on simulated experiments with known truth (no ROS).

A small focusing sample is driven by a measured-looking pulse record; the simulated rig's
physics gives the true motion, its camera films it, the tracker measures it, and the comparison
re-simulates from the measured input alone.
"""

import json
from dataclasses import replace

import cv2
import equinox as eqx
import numpy as np
import pytest

from comparison.experiment import compare_experiment, scene_of_design
from design_engine.run import smooth_input
from comparison.metrics import compare
from design_engine.auto import contact_config
from hardware_sim import camera as cam
from hardware_sim import specimen as sp
from hardware_sim.rig import MotionRecord, capture_times, centred_origin, film, specimen_motion
from metarig.trajectory import Trajectory

FPS = 1000.0
T_IN = np.arange(0.0, 0.08, 1e-4)
U_IN = 1e-3 * (1 - np.cos(2 * np.pi * 30 * np.clip(T_IN - 0.005, 0, 1 / 30)))  # A = 2 mm


def _specimen(stiffer: float = 1.0) -> sp.Specimen:
    s = sp.build(sp.SpecimenConfig(scene="focusing-24x16", nx=8, ny=6, bias_angle_deg=25.0))
    if stiffer != 1.0:
        names = ("k_stretch", "k_shear", "k_bend")
        m = s.scene.material
        m = eqx.tree_at(lambda x: tuple(getattr(x, n) for n in names), m,
                        tuple(getattr(m, n) * stiffer for n in names))
        s = sp.Specimen(s.config, replace(s.scene, material=m), s.polygons_m, {})
    return s


def _truth(specimen):
    times = capture_times(0.001, 0.07, FPS)
    traj = specimen_motion(specimen, times, MotionRecord(T_IN, U_IN), None, FPS)
    return times, traj


@pytest.fixture(scope="module")
def nominal():
    s = _specimen()
    return s, scene_of_design(json.loads(s.design_json())), *_truth(s)


def _compare(scene, times, q):
    poses = Trajectory.from_positions(times - times[0], q)
    return compare_experiment(scene, poses, times[0], T_IN, U_IN, config=contact_config())


def test_a_simulated_experiment_compared_with_its_truth_has_near_zero_error(nominal):
    _, scene, times, traj = nominal
    ec = _compare(scene, times, traj.q[1:])
    m = ec.comparison.metrics
    assert ec.input.source == "tracked"  # the driven units were seen in every frame
    assert m["velocity_nrmse"] < 0.01 and m["energy_map_correlation"] > 0.9999
    assert abs(m["target_peak_ke_rel_err"]) < 0.005 and m["max_displacement_error_m"] < 1e-5
    assert m["onset_s"] == pytest.approx(0.004, abs=5e-4) and m["lost_units"] == 0
    np.testing.assert_allclose(ec.simulated.q[0], 0.0, atol=0)  # both from the first frame


def test_twenty_percent_stiffer_ligaments_are_detected(nominal):
    _, scene, times, traj = nominal
    base = _compare(scene, times, traj.q[1:]).comparison.metrics
    _, stiff = _truth(_specimen(stiffer=1.2))
    m = _compare(scene, times, stiff.q[1:]).comparison.metrics
    assert m["velocity_nrmse"] > 3 * base["velocity_nrmse"]
    assert abs(m["target_peak_ke_rel_err"]) > 5 * abs(base["target_peak_ke_rel_err"])


def test_tracked_against_simulated_motion(nominal, tmp_path):
    """Film the truth with camera noise, track it by DIC, compare: tracking error is small
    against the signal, and the lost units are none."""
    from tracking.batch import track_source
    from tracking.calibration import Calibration
    from tracking.dic import DICConfig
    from tracking.frame_sources import open_source

    specimen, scene, times, traj = nominal
    mpp = 4e-4
    w, h = 340, 260
    origin = centred_origin(specimen.polygons_m, w, h, mpp)
    ccfg = cam.CameraConfig(width_px=w, height_px=h, fps=FPS, m_per_px=mpp, origin_px=origin,
                            noise_std=0.01, seed=0)
    for k, (_, frame, _) in enumerate(film(specimen, ccfg, traj, np.random.default_rng(0))):
        cv2.imwrite(str(tmp_path / f"{k:04d}.png"), frame)
    calib = Calibration(fps=FPS, m_per_px=mpp, origin_px=origin, y_up=True)
    tracked, bad = track_source(open_source(tmp_path), specimen.polygons_m, calib, DICConfig())
    assert not bad.any() and not tracked.lost.any()
    tracked = Trajectory.from_positions(times - times[0], tracked.q, tracked.quality,
                                        tracked.lost)
    ec = compare_experiment(scene, tracked, times[0], T_IN, U_IN, config=contact_config())
    m = ec.comparison.metrics
    # the tracking part of the error: tracked against the true motion, same fields
    truth = Trajectory.from_positions(tracked.t, traj.q[1:] - traj.q[1])
    mt = compare(ec.measured, truth, scene.unit_masses_kg(), scene.unit_inertias_kgm2(),
                 np.arange(scene.n_units), np.arange(8), m["onset_s"]).metrics
    assert m["lost_units"] == 0 and m["energy_map_correlation"] > 0.99
    # a 2 mm pulse on 8x6 units at 0.4 mm/px: differentiated camera noise dominates
    assert m["velocity_nrmse"] < 0.2 and abs(m["target_peak_ke_rel_err"]) < 0.1
    # ... and the tracking error explains it (the model adds little on top)
    assert m["velocity_nrmse"] <= 1.1 * mt["velocity_nrmse"] + 0.01


def test_the_input_is_resampled_smoothly():
    t = np.arange(0, 0.05, 1e-3)
    u = np.sin(2 * np.pi * 30 * t)
    tf, uf = smooth_input(t, u)
    assert np.median(np.diff(tf)) <= 1e-4 + 1e-12
    np.testing.assert_allclose(uf, np.sin(2 * np.pi * 30 * tf), atol=2e-4)
    fine = np.arange(0, 0.05, 5e-5)
    assert smooth_input(fine, np.sin(fine))[0].size == fine.size  # already fine: unchanged


def test_a_design_that_does_not_match_the_recording_is_refused(nominal):
    _, scene, times, traj = nominal
    poses = Trajectory.from_positions(times - times[0], traj.q[1:, :40])
    with pytest.raises(ValueError, match="does not match the recording"):
        compare_experiment(scene, poses, times[0], T_IN, U_IN)
