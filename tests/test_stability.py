"""Where methods fail, failures are reported (never plausible numbers); the automatic choice."""

import math

import pytest

from design_engine import run as run_mod
from design_engine.auto import Choice, choose_config, contact_config, max_angular_frequency
from design_engine.fixed_step import FixedStepVerlet
from design_engine.modal import modal_analysis
from design_engine.run import simulate_scene
from design_engine.scenes import build_scene
from design_engine.simulate import SimulationError, SolverConfig
from gradcheck import directional_check


@pytest.fixture(scope="module")
def small():
    return build_scene("focusing-24x16", nx=8, ny=6, amplitude_m=2e-3)


def test_power_iteration_finds_the_highest_mode(small):
    omega = max_angular_frequency(small)
    f_dense = modal_analysis(small).frequencies_hz[-1]
    assert omega / (2 * math.pi) * 1e3 == pytest.approx(f_dense, rel=1e-3)


@pytest.mark.parametrize("factor", [1.15, 1.6])
def test_fixed_step_above_the_stability_limit_is_reported(small, factor):
    dt = factor * 2.0 / max_angular_frequency(small)
    with pytest.raises(SimulationError, match="diverged|non-finite|stability|barrier"):
        simulate_scene(small, SolverConfig(solver=FixedStepVerlet(max_dt=dt)))


def test_fixed_step_below_the_limit_matches_the_adaptive_reference(small):
    ref = simulate_scene(small, SolverConfig(rtol=1e-10, atol=1e-9)).metrics["target_ke_mean_J"]
    dt = 0.6 * 2.0 / max_angular_frequency(small)
    for dtype in ("float64", "float32"):
        got = simulate_scene(small, SolverConfig(solver=FixedStepVerlet(max_dt=dt), dtype=dtype))
        assert got.metrics["target_ke_mean_J"] == pytest.approx(ref, rel=5e-3)


def test_fixed_step_gradient_matches_finite_differences(small):
    config = SolverConfig(solver=FixedStepVerlet(max_dt=0.6 * 2.0 / max_angular_frequency(small)))
    directional_check(small, config, h=1e-4, seed=4, rel=1e-5)


def test_contact_stiffened_precompression_breaks_a_too_large_fixed_step():
    # 8 % pre-compression closes voids onto the contact barrier: a step that is fine at rest fails,
    # and the failure is detected (never returned as numbers)
    scene = build_scene("protection-24x18", nx=8, ny=8, strain=0.08)
    dt = 0.9 * 2.0 / max_angular_frequency(scene)
    with pytest.raises(SimulationError, match="diverged|non-finite|barrier"):
        simulate_scene(scene, SolverConfig(solver=FixedStepVerlet(max_dt=dt)))


def test_automatic_choice_says_what_it_picked_and_falls_back(small, monkeypatch):
    choice = choose_config(small)
    assert isinstance(choice.config.solver, FixedStepVerlet)
    assert any("Verlet" in r for r in choice.reasons)
    run = simulate_scene(small)
    assert any("Verlet" in r for r in run.metrics["solver"]["choice"])
    # a choice that cannot work is replaced by the adaptive solver, and the summary says so
    bad = Choice(SolverConfig(solver=FixedStepVerlet(max_dt=5 * choice.config.solver.max_dt)),
                 ("deliberately unstable",))
    monkeypatch.setattr(run_mod, "default_choice", lambda scene: bad)
    run = simulate_scene(small)
    assert run.metrics["solver"]["solver"] == "Dopri8"
    assert any("fell back" in r for r in run.metrics["solver"]["choice"])


def test_full_model_can_be_forced(small):
    assert choose_config(small, full_model=True).config == SolverConfig()


def test_contact_left_out_only_while_it_is_exactly_zero():
    # voids of 2 deg close past the -10 deg cutoff under the pulse: the no-contact solve is
    # detected as invalid and repeated with contact (Dopri8), so the result is that model's
    scene = build_scene("focusing-24x16", nx=8, ny=6, bias_angle_deg=44.0, amplitude_m=6e-3)
    auto = simulate_scene(scene)
    assert auto.metrics["solver"]["use_contact"] is True
    assert "re-solved with contact" in auto.metrics["solver"]["choice"][-1]
    full = simulate_scene(scene, contact_config())
    assert auto.metrics["target_ke_mean_J"] == pytest.approx(full.metrics["target_ke_mean_J"],
                                                             rel=1e-12)


def test_precompressed_scenes_use_the_contact_configuration():
    choice = choose_config(build_scene("protection-24x18", nx=8, ny=8, strain=0.05))
    assert choice.config == contact_config() and "Dopri8" in choice.reasons[0]
