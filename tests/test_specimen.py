"""The simulated rig's specimen is not its model: each imperfection of a fabricated sample, its
size, its switch, and the way its settings reach the rig (`hardware_sim.specimen`).

The scene is the 8x6 focusing lattice under a 2 mm, 30 Hz pulse with a fixed asymmetric design
(`discrepant.asymmetric_design`: the periodic lattice's symmetric response tips over at any
imperfection).
"""

import dataclasses
import json

import numpy as np
import pytest
from discrepant import asymmetric_design, raised_cosine

from hardware_sim import specimen as sp
from hardware_sim.rig import MotionRecord, capture_times, specimen_motion

OFF = {"tolerance_m": 0.0, "ligament_scatter": 0.0, "damping_scatter": 0.0,
       "thickness_error": 0.0, "friction_hz": 0.0}
T_IN, U_IN = raised_cosine(2e-3, 0.08)
TIMES = capture_times(0.001, 0.07, 1000.0)


@pytest.fixture(scope="module")
def config(tmp_path_factory):
    path = asymmetric_design(tmp_path_factory.mktemp("design") / "design.json")
    return sp.SpecimenConfig(scene="focusing-24x16", design_path=str(path), seed=3)


def _build(cfg, **imperfections):
    return sp.build(dataclasses.replace(cfg, imperfections=sp.Imperfections(**imperfections)))


def _motion(s):
    return specimen_motion(s, TIMES, MotionRecord(T_IN, U_IN), None, 1000.0)


def _same_material(a, b):
    return all(np.array_equal(np.asarray(getattr(a, f)), np.asarray(getattr(b, f)))
               for f in ("k_stretch", "k_shear", "k_bend", "k_contact", "damping_u",
                         "damping_theta", "density", "contact_min", "contact_cutoff"))


@pytest.fixture(scope="module")
def nominal(config):
    s = sp.build(dataclasses.replace(config, imperfections=sp.NOMINAL))
    return s, _motion(s)


def test_each_imperfection_switched_off_gives_back_the_nominal_truth_exactly(config, nominal):
    s0, motion0 = nominal
    full = _build(config)
    # level 0: the nominal specimen, the same scene and, solved, the same motion to the bit
    zero = _build(config, level=0.0)
    assert np.array_equal(zero.scene.design, s0.scene.design) and zero.imperfections == {}
    assert _same_material(zero.scene.material, s0.scene.material)
    assert np.array_equal(_motion(zero).q, motion0.q)
    # each one off (the others at their defaults): its part of the truth is the nominal one,
    # and the others' draws are those of the full specimen (one seeded stream each)
    m0, mf = s0.scene.material, full.scene.material
    s = _build(config, tolerance_m=0.0)
    assert np.array_equal(s.scene.design, s0.scene.design)
    assert _same_material(s.scene.material.replaced(damping_u=0.0, damping_theta=0.0),
                          mf.replaced(damping_u=0.0, damping_theta=0.0))
    s = _build(config, ligament_scatter=0.0, thickness_error=0.0)
    assert all(getattr(s.scene.material, n) == getattr(m0, n)
               for n in ("k_stretch", "k_shear", "k_bend"))
    assert np.array_equal(s.scene.design, full.scene.design)
    s = _build(config, damping_scatter=0.0, friction_hz=0.0)
    assert s.scene.material.damping_u == m0.damping_u
    assert s.scene.material.damping_theta == m0.damping_theta
    assert np.array_equal(s.scene.material.k_bend, mf.k_bend)
    # every one off: the nominal specimen again
    s = _build(config, **OFF)
    assert np.array_equal(s.scene.design, s0.scene.design)
    assert _same_material(s.scene.material, m0)


def test_each_imperfection_has_its_stated_size(config, nominal):
    s0 = nominal[0]
    d = sp.Imperfections()
    m0 = s0.scene.material
    # cut tolerance: every design coordinate (vertex) moved by N(0, tolerance)
    s = _build(config, **{**OFF, "tolerance_m": d.tolerance_m})
    dx = (s.scene.design - s0.scene.design) / 1e3
    assert np.std(dx) == pytest.approx(d.tolerance_m, rel=0.15) and abs(np.mean(dx)) < 2e-5
    assert np.abs(s.polygons_m - s.nominal_polygons_m).max() < 6 * d.tolerance_m
    np.testing.assert_array_equal(s.nominal_polygons_m, s0.polygons_m)
    # the thickness law: bending as t^3, stretch and shear as t, contact untouched
    s = _build(config, **{**OFF, "thickness_error": -0.1})
    m = s.scene.material
    assert m.k_bend == pytest.approx(m0.k_bend * 0.9**3, rel=1e-15)
    assert m.k_shear == pytest.approx(m0.k_shear * 0.9, rel=1e-15)
    assert m.k_stretch == pytest.approx(m0.k_stretch * 0.9, rel=1e-15)
    assert m.k_contact == m0.k_contact
    # ligament scatter: one log-normal factor per bond for its three stiffnesses
    s = _build(config, **{**OFF, "ligament_scatter": 0.1})
    f = np.asarray(s.scene.material.k_bend) / m0.k_bend
    assert f.shape == (s.scene.lattice.n_bonds,)
    np.testing.assert_allclose(np.asarray(s.scene.material.k_shear) / m0.k_shear, f, rtol=1e-14)
    assert np.std(np.log(f)) == pytest.approx(0.1, rel=0.25)
    # damping scatter per unit; friction adds gamma m_b and gamma J_b (engine units)
    s = _build(config, **{**OFF, "damping_scatter": 0.2})
    g = np.asarray(s.scene.material.damping_u) / m0.damping_u
    assert g.shape == (s.scene.n_units,) and np.std(np.log(g)) == pytest.approx(0.2, rel=0.3)
    np.testing.assert_allclose(np.asarray(s.scene.material.damping_theta) / m0.damping_theta, g)
    s = _build(config, **{**OFF, "friction_hz": 10.0})
    np.testing.assert_allclose(s.scene.material.damping_u - m0.damping_u,
                               1e-2 * 1e3 * s0.scene.unit_masses_kg(), rtol=1e-12)
    np.testing.assert_allclose(s.scene.material.damping_theta - m0.damping_theta,
                               1e-2 * 1e9 * s0.scene.unit_inertias_kgm2(), rtol=1e-12)


def test_the_comparison_error_grows_with_the_discrepancy_level(config, nominal):
    """The comparison of the specimen's true motion (the rig's ground-truth poses) with the
    nominal model's simulation of the same input: about zero at level 0 (measured velocity
    NRMSE 0.0014), and an error that grows in proportion to the level (0.034 at 0.5, 0.066 at
    1; target peak kinetic energy +4.7 %, +9.4 %); the design the specimen publishes is the
    nominal one."""
    from comparison.experiment import compare_experiment, scene_of_design
    from design_engine.solve.policy import contact_config
    from metarig.trajectory import Trajectory

    s0, motion0 = nominal
    scene = scene_of_design(json.loads(s0.design_json()))

    def compared(motion):
        poses = Trajectory.from_positions(TIMES - TIMES[0], motion.q[1:])
        return compare_experiment(scene, poses, TIMES[0], T_IN, U_IN,
                                  config=contact_config()).comparison.metrics

    m = {0.0: compared(motion0)}
    assert m[0.0]["velocity_nrmse"] < 0.01 and m[0.0]["energy_map_correlation"] > 0.9999
    for level in (0.5, 1.0):
        s = _build(config, level=level)
        m[level] = compared(_motion(s))
        doc = json.loads(s.design_json())
        np.testing.assert_allclose(np.asarray(doc["design_m"]) * 1e3, s0.scene.design,
                                   rtol=0, atol=1e-12)
        assert doc["specimen_imperfections"]["level"] == level
    v = {k: x["velocity_nrmse"] for k, x in m.items()}
    assert 0.015 < v[0.5] < v[1.0] < 0.2, m
    assert v[1.0] / v[0.5] == pytest.approx(2.0, rel=0.25), m
    peak = {k: x["target_peak_ke_rel_err"] for k, x in m.items()}
    assert 0.02 < peak[0.5] < peak[1.0] < 0.2, m
    assert m[1.0]["energy_map_correlation"] < m[0.5]["energy_map_correlation"] < 0.99999, m


def test_the_default_imperfect_specimen_end_to_end_through_camera_and_tracker(config, nominal,
                                                                            tmp_path):
    """The default specimen filmed (its true outlines), tracked by DIC with the outlines of the
    design it publishes, compared with the nominal model (test_comparison_experiment's 100 Hz
    filmed pulse, camera noise seed 0): the tracker does as well as on a nominal specimen
    (measured 0.053 velocity NRMSE against the truth, nominal 0.053), and the comparison sees
    the specimen (measured 0.239, 4.5x the tracking part; a nominal specimen 0.051)."""
    from test_comparison_experiment import _film_and_track

    from comparison.experiment import scene_of_design
    from comparison.metrics import compare
    from metarig.trajectory import Trajectory

    s = sp.build(config)
    assert s.config.imperfections == sp.Imperfections()  # the defaults
    scene = scene_of_design(json.loads(s.design_json()))
    traj, tracked, ec = _film_and_track(s, scene, 0, tmp_path)
    m = ec.comparison.metrics
    mid = traj.q[1::3]
    truth = Trajectory.from_positions(tracked.t, mid - mid[0])
    mt = compare(ec.measured, truth, scene.unit_masses_kg(), scene.unit_inertias_kgm2(),
                 np.arange(scene.n_units), np.arange(8), m["onset_s"]).metrics
    assert mt["velocity_nrmse"] < 0.06 and m["lost_units"] == 0
    assert 3 * mt["velocity_nrmse"] < m["velocity_nrmse"] < 0.4, (m, mt)
    assert m["energy_map_correlation"] > 0.999


def test_the_imperfections_are_node_parameters_and_rig_flags(tmp_path):
    from ros_nodes import params as P
    from ros_nodes.cli_rig import _node_params, _parser, _plan

    names = {s.name for s in P.flat_fields(P.CameraNodeConfig)}
    assert {f"specimen.{f.name}" for f in dataclasses.fields(sp.Imperfections)} <= names
    plan = _plan(_parser().parse_args(["--specimen-friction-hz", "0", "--specimen-level", "2"]))
    assert plan.specimen == sp.Imperfections(level=2.0, friction_hz=0.0)
    camera = _node_params(plan, tmp_path, None)["camera"]
    assert camera["specimen.level"] == 2.0 and camera["specimen.friction_hz"] == 0.0
    assert camera["specimen.tolerance_m"] == sp.Imperfections().tolerance_m
    cfg = P.from_flat(P.CameraNodeConfig, {k: v for k, v in camera.items()
                                           if k != "use_sim_time"})
    assert cfg.specimen == plan.specimen
    with pytest.raises(P.ConfigError, match="specimen.ligament_scatter"):
        _node_params(_plan(_parser().parse_args(["--specimen-ligament-scatter", "-1"])),
                     tmp_path, None)
