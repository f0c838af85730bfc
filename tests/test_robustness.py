"""Robustness map (Fig. 2C): batched grid = single simulations, policy per point, CLI, Dask, errors.

A small 8x6 periodic (25 deg) focusing design keeps the file fast. Its grid stays at small
amplitudes (0.05 s and 0.1 s): on so small a lattice larger inputs make the response chaotic
(a 1e-10 change of the amplitude changes R by percent at 0.5 s), so no two solvers agree there.
The whole file takes about 30 s on two loaded cores with an empty compilation cache, the Dask
test (two local worker processes) about 10 s of it.
"""

import dataclasses
import json
import logging
import math
import os
import platform

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from design_engine.commands.robustness import robustness_main
from design_engine.design.design_io import save_design
from design_engine.physics.lattice import periodic_design, quads
from design_engine.physics.scenes import build_scene
from design_engine.solve.objectives import region_energy, region_energy_ratio
from design_engine.solve.policy import Choice
from design_engine.solve.run import compiled_simulator, default_choice, simulate_scene
from design_engine.sweeps import robustness as rb

S_M = 0.015  # lattice spacing, m
FREQS = (20.0, 40.0)  # Hz
AMPS_S = (0.05, 0.1)  # units of the spacing
AMPS_M = tuple(round(v * S_M, 12) for v in AMPS_S)
# grid points per batch: the 2x2 grid in two batches, and every map of the file (the 2-point
# fallback grid, the CLI's 6-point resume, the Dask chunks) in batches of this one compiled
# program (a chunk of 4 compiled a second Verlet batch program for the same checks)
CHUNK = 2
# float32 (the automatic Verlet choice): the same solve batched or alone differs by rounding,
# which the dynamics amplify to ~1e-4 relative in R on this lattice (1e-5 on the 24x16 one)
F32_RTOL = 5e-4


def _x(bias_deg=25.0):
    return periodic_design(quads(8, 6), math.radians(bias_deg))


@pytest.fixture(scope="module")
def design_file(tmp_path_factory):
    return save_design(tmp_path_factory.mktemp("design") / "design.json", quads(8, 6), _x())


@pytest.fixture(scope="module")
def scene():
    return build_scene("focusing-24x16", nx=8, ny=6, design=_x())


@pytest.fixture(scope="module")
def rmap(scene):
    return rb.robustness_map(scene, FREQS, AMPS_M, chunk=CHUNK)


def tied_scene(f_hz, a_m, f_min_hz=FREQS[0]):
    """One grid point's scene built independently: window 2 / f_min, delay 0.1 / f_min."""
    sc = build_scene("focusing-24x16", nx=8, ny=6, design=_x(), frequency_hz=f_hz,
                     amplitude_m=a_m, periods=2.0 * f_hz / f_min_hz)
    return dataclasses.replace(sc, loading=dataclasses.replace(sc.loading,
                                                               delay=0.1 / (f_min_hz / 1e3)))


def _f64(sol):
    return jax.tree_util.tree_map(
        lambda a: a.astype(jnp.float64) if jnp.issubdtype(a.dtype, jnp.floating) else a, sol)


def _load(path):
    doc = json.loads(path.read_text())
    return doc, np.array([[np.nan if v is None else v for v in row] for row in doc["ratio"]])


# ------------------------------------------------------------------------------ engine


def test_batched_grid_equals_single_simulations_with_the_automatic_policy(scene, rmap):
    assert rmap.ratio.shape == rmap.target_ke_mean_J.shape == (2, 2)
    np.testing.assert_array_equal(rmap.frequencies_hz, FREQS)
    np.testing.assert_array_equal(rmap.amplitudes_m, AMPS_M)
    assert rmap.timing == {"tied_to_hz": 20.0, "delay_s": pytest.approx(0.1 / 20),
                           "window_s": pytest.approx(2 / 20), "n_samples": 200}
    assert rmap.configs[0]["solver"]["solver"] == "FixedStepVerlet"
    assert not rmap.configs[0]["solver"]["use_contact"]
    assert (rmap.point_config == 0).all() and rmap.failures == ()
    for i, f in enumerate(FREQS):
        for j, a in enumerate(AMPS_M):
            sc = tied_scene(f, a)
            assert sc.sample_times[-1] == pytest.approx(100.0) and sc.sample_times.size == 200
            run = simulate_scene(sc)
            assert run.metrics["solver"]["solver"] == "FixedStepVerlet"
            ids = sc.targets["target"]
            ref = float(region_energy_ratio(_f64(run.solution), ids))
            assert rmap.ratio[i, j] == pytest.approx(ref, rel=F32_RTOL)
            assert rmap.ratio[i, j] == pytest.approx(
                run.metrics["targets"]["target"]["ratio_to_rest"], rel=F32_RTOL)
            assert rmap.target_ke_mean_J[i, j] == pytest.approx(run.metrics["target_ke_mean_J"],
                                                                rel=F32_RTOL)
    # the map is not flat: frequency and amplitude both change R by more than the tolerance
    assert abs(rmap.ratio[0, 0] / rmap.ratio[1, 0] - 1) > 20 * F32_RTOL
    assert abs(rmap.ratio[0, 0] / rmap.ratio[0, 1] - 1) > 20 * F32_RTOL


def test_batched_grid_equals_per_point_calls_of_the_same_simulator_in_float64(scene):
    """Batching itself is exact: in float64 the vmap batch and per-point calls agree to 1e-9."""
    cfg = dataclasses.replace(default_choice(scene).config, dtype="float64")
    pts = rb.grid_points(FREQS, AMPS_M)
    res = rb.evaluate_points(scene, pts, f_min_hz=20.0, chunk=CHUNK, choice=Choice(cfg, ("f64",)))
    ts = rb.tied_sample_times(scene, 20.0)
    sim = compiled_simulator(scene, cfg, ts)
    for k, (f, a) in enumerate(pts):
        sol = sim(jnp.asarray(scene.design), scene.material, tied_scene(f, a).loading,
                  jnp.asarray(ts))
        ids = scene.targets["target"]
        assert res["ratio"][k] == pytest.approx(float(region_energy_ratio(sol, ids)), rel=1e-9)
        assert res["target_ke_mean_J"][k] == pytest.approx(
            float(region_energy(sol, ids)) / 200 * 1e-3, rel=1e-9)
        assert res["config"][k] == 0


def test_a_point_whose_fixed_step_solve_fails_is_resolved_with_contact(scene):
    """0.9 s on this lattice: Verlet without contact diverges; the point is re-run (batched)
    with the fallback, adaptive Dopri8 and contact, as `simulate_scene` does, and the map says
    so."""
    m = rb.robustness_map(scene, (20.0,), (AMPS_M[0], 0.9 * S_M), chunk=CHUNK)
    assert m.point_config[0, 0] == 0 and m.point_notes[0, 0] == ""
    c = m.configs[m.point_config[0, 1]]
    assert m.point_config[0, 1] == 1
    assert c["solver"]["solver"] == "Dopri8" and c["solver"]["use_contact"]
    assert "fell back to adaptive Dopri8" in c["reasons"][0]
    assert "FixedStepVerlet" in m.point_notes[0, 1]
    assert np.isfinite(m.ratio).all() and m.failures == ()
    single = simulate_scene(tied_scene(20.0, 0.9 * S_M))
    assert single.metrics["solver"]["solver"] == "Dopri8"


def test_a_point_that_fails_with_every_configuration_is_nan_and_listed(scene, monkeypatch):
    verlet = default_choice(scene).config
    monkeypatch.setattr(rb, "fallback_config", lambda: (verlet, "no fallback"))  # nothing else
    m = rb.robustness_map(scene, (20.0,), (AMPS_M[0], 0.9 * S_M), chunk=CHUNK)
    assert np.isfinite(m.ratio[0, 0]) and np.isnan(m.ratio[0, 1])
    assert np.isnan(m.target_ke_mean_J[0, 1]) and m.point_config[0, 1] == -1
    assert len(m.failures) == 1
    fail = m.failures[0]
    assert fail["frequency_hz"] == 20.0 and fail["amplitude_m"] == pytest.approx(0.9 * S_M)
    assert "diverged" in fail["reason"] and "every configuration" in fail["reason"]


def test_chunk_function_takes_plain_data(scene, rmap):
    pts = rb.grid_points(FREQS, AMPS_M)[1:3]
    res = rb.robustness_chunk(scene.design / 1e3, scene.lattice.describe(), pts,
                              f_min_hz=20.0, omega_rad_per_ms=default_choice(scene).omega_max,
                              chunk=CHUNK)
    json.dumps(res)  # plain data only
    np.testing.assert_allclose(res["ratio"], rmap.ratio.reshape(-1)[1:3], rtol=F32_RTOL)
    with pytest.raises(ValueError, match="differs"):
        rb.design_scene(scene.design / 1e3, quads(8, 6, spacing=20.0).describe())


# ------------------------------------------------------------------------------ CLI


def _cli(design, out, *extra, freqs="20,40"):
    return robustness_main([str(design), "--out", str(out), "--frequencies", freqs,
                            "--amplitudes", ",".join(map(str, AMPS_S)), "--chunk", str(CHUNK),
                            "--quiet", *extra])


def test_cli_writes_json_and_png_and_a_rerun_reuses_the_finished_points(design_file, rmap,
                                                                         tmp_path, caplog):
    out = tmp_path / "map"
    assert _cli(design_file, out) == 0
    doc, ratio = _load(out / "robustness.json")
    assert doc["status"] == "complete" and doc["format"] == "metarig-robustness/1"
    assert doc["frequencies_hz"] == list(FREQS) and doc["amplitudes_m"] == list(AMPS_M)
    assert doc["amplitudes_over_spacing"] == pytest.approx(AMPS_S)
    assert ratio.shape == (2, 2) and np.asarray(doc["target_ke_mean_J"]).shape == (2, 2)
    np.testing.assert_allclose(ratio, rmap.ratio, rtol=1e-12)  # same batch, same program
    assert doc["config"] == [[0, 0], [0, 0]]
    assert doc["configs"][0]["solver"]["solver"] == "FixedStepVerlet"
    assert doc["timing"]["delay_s"] == pytest.approx(0.005)
    assert doc["run"]["computed_points"] == 4 and doc["run"]["reused_points"] == 0
    assert doc["machine"]["cpu_count"] >= 1 and doc["run"]["wall_s"] > 0
    png = (out / "robustness.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000

    caplog.clear()
    with caplog.at_level(logging.INFO, logger="metarig.robustness"):
        assert _cli(design_file, out) == 0
    doc2, ratio2 = _load(out / "robustness.json")
    assert doc2["run"]["computed_points"] == 0 and doc2["run"]["reused_points"] == 4
    assert doc2["run"]["chunks"] == 0
    np.testing.assert_array_equal(ratio2, ratio)
    assert any("4 of 4 grid points already in" in r.getMessage() for r in caplog.records)


def test_an_interrupted_cli_run_resumes_with_the_missing_chunks_only(design_file, rmap, tmp_path,
                                                                     monkeypatch):
    out = tmp_path / "map"
    real, calls = rb.evaluate_points, []

    def interrupted(*args, **kwargs):  # the second chunk never finishes
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(rb, "evaluate_points", interrupted)
    with pytest.raises(KeyboardInterrupt):
        _cli(design_file, out, freqs="20,30,40")  # 6 points: 3 chunks of 2
    doc, ratio = _load(out / "robustness.json")
    assert doc["status"] == "partial" and doc["grid_points_done"] == 2
    assert np.isfinite(ratio[0]).all() and np.isnan(ratio[1:]).all()  # f-major: 20 Hz done

    monkeypatch.setattr(rb, "evaluate_points", real)
    assert _cli(design_file, out, freqs="20,30,40") == 0
    doc, ratio = _load(out / "robustness.json")
    assert doc["status"] == "complete" and np.isfinite(ratio).all()
    assert doc["run"]["computed_points"] == 4 and doc["run"]["reused_points"] == 2
    np.testing.assert_allclose(ratio[[0, 2]], rmap.ratio, rtol=F32_RTOL)


def test_dask_workers_give_the_same_map_as_the_in_process_path(design_file, tmp_path):
    assert CHUNK == 2  # 2 chunks of the 2x2 grid, one per worker
    assert _cli(design_file, tmp_path / "local") == 0
    assert _cli(design_file, tmp_path / "dask", "--workers", "2") == 0
    local, r_local = _load(tmp_path / "local" / "robustness.json")
    dask, r_dask = _load(tmp_path / "dask" / "robustness.json")
    assert dask["status"] == "complete" and dask["run"]["workers"] == 2
    assert dask["run"]["chunks"] == 2 and dask["run"]["computed_points"] == 4
    here = f"{platform.node()}:{os.getpid()}"
    assert local["run"]["processes"] == [here]
    assert dask["run"]["processes"] and here not in dask["run"]["processes"]  # on the workers
    np.testing.assert_allclose(r_dask, r_local, rtol=1e-6)  # same batch program in each process
    assert dask["config"] == local["config"] and dask["configs"] == local["configs"]


# ------------------------------------------------------------------------------ errors


@pytest.mark.parametrize("make, extra, message", [
    ("missing", [], "does not exist"),
    ("damaged", [], "not readable JSON"),
    ("good", ["--frequencies", "20,-5"], "frequencies must be positive"),
    ("good", ["--frequencies", "20,abc"], "comma list of numbers"),
    ("good", ["--amplitudes", "0.1,0"], "amplitudes must be positive"),
    ("good", ["--amplitudes", "0.5,2.0"], "not below 2 s"),
    ("good", ["--amplitudes", "31", "--amplitude-unit", "mm"], "not below 2 s"),
    ("good", ["--workers", "2", "--scheduler", "tcp://127.0.0.1:1"], "not allowed with"),
    ("good", ["--workers", "0"], "at least 1"),
    ("good", ["--scheduler", ""], "--scheduler is empty"),
    ("good", ["--chunk", "0"], "at least 1"),
    ("good", ["--scene", "nope"], "unknown scene"),
    ("other-map", [], "the map of another design"),
    ("cut-map", [], "robustness.json exists but cannot be resumed (damaged?"),
])
def test_bad_inputs_end_in_one_error_line_and_exit_code_2(design_file, tmp_path, capsys, make,
                                                          extra, message):
    out = tmp_path / "out"
    path = {"good": design_file, "missing": tmp_path / "nope.json",
            "damaged": tmp_path / "damaged.json", "other-map": tmp_path / "other.json",
            "cut-map": design_file}[make]
    if make == "damaged":
        path.write_text('{"format": "metarig-design/1", "lattice": ')
    if make == "other-map":  # --out already holds the map of another design
        save_design(path, quads(8, 6), _x(20.0))
        out.mkdir()
        fingerprint = {"scene": "focusing-24x16", "lattice": quads(8, 6).describe(),
                       "design_sha256": "0" * 64,
                       "timing": rb.tied_timing(build_scene("focusing-24x16", nx=8, ny=6), 20.0)}
        (out / "robustness.json").write_text(json.dumps(
            {"format": "metarig-robustness/1", "fingerprint": fingerprint, "points": [],
             "configs": []}))
    if make == "cut-map":  # a map cut to half its bytes: refused, and left as it is
        out.mkdir()
        text = json.dumps({"format": "metarig-robustness/1", "points": [], "configs": []})
        (out / "robustness.json").write_text(text[:len(text) // 2])
    before = {f.name: f.read_bytes() for f in out.iterdir()} if out.exists() else {}
    capsys.readouterr()
    rc = robustness_main([str(path), "--out", str(out), "--quiet", *extra])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2
    assert len(err) == 1, err
    assert err[0].startswith("metarig robustness: error: ") and message in err[0], err[0]
    assert ({f.name: f.read_bytes() for f in out.iterdir()} if out.exists() else {}) == before


def test_missing_out_is_a_one_line_error(design_file, capsys):
    assert robustness_main([str(design_file)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--out" in err[0]

