"""Figures and Rerun recording of a comparison, on a synthetic lattice of squares (no ROS)."""

import importlib.util
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from comparison import rerun_log
from comparison.metrics import compare
from comparison.plots import posed_outlines, snapshot_indices, window_samples, write_plots
from metarig.trajectory import Trajectory

NX, NY, PITCH, SIDE = 6, 4, 0.015, 0.012
ONSET = 0.01
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def squares(nx=NX, ny=NY, pitch=PITCH, side=SIDE) -> np.ndarray:
    """[nx * ny, 4, 2] counter-clockwise squares, row-major with x fastest, m."""
    cx, cy = np.meshgrid(np.arange(nx) * pitch, np.arange(ny) * pitch)
    c = np.stack([cx.ravel(), cy.ravel()], axis=-1)
    h = side / 2
    return c[:, None, :] + np.array([[-h, -h], [h, -h], [h, h], [-h, h]])


def wave(polygons, nt=60, fps=1000.0, scale=1.0, lost_unit=None):
    """A pulse travelling along x from ONSET on; optionally one unit lost in one frame."""
    t = np.arange(nt) / fps
    x = polygons.mean(axis=1)[:, 0]
    tau = np.clip(t[:, None] - ONSET - x[None, :] / 5.0, 0.0, None)
    s = np.sin(2 * np.pi * 30 * tau) * (tau > 0)
    q = np.zeros((nt, len(x), 3))
    q[..., 0] = scale * 1e-3 * s
    q[..., 2] = scale * 2e-2 * s
    lost = None
    if lost_unit is not None:
        lost = np.zeros((nt, len(x)), bool)
        lost[nt // 2, lost_unit] = True
        q[lost] = np.nan
    quality = np.clip(0.97 - 0.1 * np.abs(s), -1, 1)
    return Trajectory.from_positions(t, q, quality=quality, lost=lost)


@pytest.fixture(scope="module")
def case():
    polys = squares()
    n = len(polys)
    sim, exp = wave(polys), wave(polys, scale=1.15, lost_unit=7)
    target = np.array([n - 2, n - 1])
    row = np.arange(NX)  # the bottom row
    mass, inertia = np.full(n, 2e-3), np.full(n, 5e-8)
    c = compare(exp, sim, mass, inertia, target, row, onset_s=ONSET)
    return {
        "polys": polys,
        "sim": sim,
        "exp": exp,
        "target": target,
        "row": row,
        "comparison": c,
        "q_exp": window_samples(c, exp.t, exp.q),
        "q_sim": window_samples(c, sim.t, sim.q),
    }


def test_posed_outlines_rotate_about_the_centroid_and_translate():
    sq = squares(1, 1)
    moved = posed_outlines(sq, np.array([[0.001, -0.002, np.pi / 2]]))
    assert moved.shape == (1, 4, 2)
    np.testing.assert_allclose(moved.mean(axis=1), [[0.001, -0.002]], atol=1e-15)
    np.testing.assert_allclose(moved[0, 0], sq[0, 1] + [0.001, -0.002], atol=1e-15)
    batched = posed_outlines(sq, np.zeros((5, 1, 3)))
    assert batched.shape == (5, 1, 4, 2) and np.allclose(batched[3], sq)


def test_window_samples_match_the_comparison(case):
    c = case["comparison"]
    assert case["q_exp"].shape == (len(c.t), len(case["polys"]), 3)
    with pytest.raises(ValueError, match="not the trajectories"):
        window_samples(c, case["sim"].t[:-3], case["sim"].q[:-3])
    idx = snapshot_indices(c)
    assert 3 <= idx.size <= 4 and np.all(np.diff(idx) > 0)
    assert int(np.nanargmax(c.target_ke_sim)) in idx


def test_every_png_is_written(case, tmp_path):
    c, exp = case["comparison"], case["exp"]
    paths = write_plots(
        tmp_path,
        c,
        case["polys"],
        case["q_exp"],
        case["q_sim"],
        case["target"],
        case["row"],
        quality=exp.quality,
        lost=exp.lost,
        t_frames_s=exp.t - ONSET,
    )
    names = {p.name for p in paths}
    assert names == {
        "velocity_maps.png",
        "target_ke.png",
        "row_peak_ke.png",
        "tracking_quality.png",
    }
    for p in paths:
        assert p.read_bytes()[:8] == PNG_MAGIC
        assert 10_000 < p.stat().st_size < 1_500_000, p.name
    without = write_plots(
        tmp_path / "no_quality",
        c,
        case["polys"],
        case["q_exp"],
        case["q_sim"],
        case["target"],
        case["row"],
    )
    assert len(without) == 3


def _frames(c, h=90, w=120):
    rng = np.random.default_rng(0)
    return rng.integers(0, 255, size=(len(c.t), h, w), dtype=np.uint8)


def _read_back(path):
    from rerun.chunk import RrdReader

    reader = RrdReader(path)
    (recording,) = reader.recordings()
    blueprints = reader.blueprints()
    chunks = reader.stream(store=recording).to_chunks()
    entities = {ch.entity_path for ch in chunks}
    timelines = set().union(*(ch.timeline_names for ch in chunks))
    bp_chunks = [ch for b in blueprints for ch in reader.stream(store=b).to_chunks()]
    views = set()  # (kind, origin) of every view of the blueprint
    for ch in bp_chunks:
        if ch.entity_path.startswith("/view/") and ch.entity_path.count("/") == 2:
            cols = ch.to_record_batch()
            kind = cols.column("ViewBlueprint:class_identifier").to_pylist()[-1][0]
            origin = cols.column("ViewBlueprint:space_origin").to_pylist()[-1][0]
            views.add((kind, origin))
    return recording, entities, timelines, {ch.entity_path for ch in bp_chunks}, views, chunks


def _first_strips(chunks, entity):
    (ch,) = [ch for ch in chunks if ch.entity_path == entity and not ch.is_static]
    return ch.to_record_batch().column("LineStrips2D:strips").to_pylist()[0]


@pytest.mark.parametrize("with_frames", [True, False])
def test_rrd_holds_the_views_series_timeline_and_blueprint(case, tmp_path, with_frames):
    c = case["comparison"]
    camera_kw = {"frames": _frames(c), "m_per_px": 1e-3, "origin_px": (20.0, 75.0)}
    path = rerun_log.write_rrd(
        tmp_path / "comparison.rrd",
        c,
        case["polys"],
        case["q_exp"],
        case["q_sim"],
        case["target"],
        recording_id="run-test",
        **(camera_kw if with_frames else {}),
    )
    recording, entities, timelines, bp_entities, views, chunks = _read_back(path)
    assert recording.application_id == rerun_log.APPLICATION_ID
    assert recording.recording_id == "run-test"
    expected = {
        "/experiment/units",
        "/experiment/speed",
        "/experiment/target",
        "/simulation/units",
        "/simulation/speed",
        "/simulation/target",
        "/series/target_ke/experiment",
        "/series/target_ke/simulation",
        "/series/velocity_error",
        "/series/displacement_error/max",
        "/summary",
    }
    camera = {"/camera/image", "/camera/outlines", "/camera/target"}
    assert expected <= entities
    assert camera <= entities if with_frames else not camera & entities
    assert rerun_log.TIMELINE in timelines
    units = [ch for ch in chunks if ch.entity_path == "/experiment/units" and not ch.is_static]
    assert sum(ch.num_rows for ch in units) == len(c.t)  # one row of outlines per sample
    # unit 0 at the onset (at rest): closed outline, mm with y negated; pixels + 0.5 on camera
    sq = case["polys"][0]
    first = np.array(_first_strips(chunks, "/experiment/units")[0])
    np.testing.assert_allclose(first, np.r_[sq, sq[:1]] * [1e3, -1e3], atol=1e-5)
    if with_frames:
        px = np.array(_first_strips(chunks, "/camera/outlines")[0])
        np.testing.assert_allclose(px, np.r_[sq, sq[:1]] * [1e3, -1e3] + [20.5, 75.5], atol=1e-4)
    # the blueprint is a store of its own: a viewport, its containers and its views
    assert "/viewport" in bp_entities
    assert views == {
        ("2D", "experiment"),
        ("2D", "simulation"),
        ("TimeSeries", "series/target_ke"),
        ("TimeSeries", "series/velocity_error"),
        ("TimeSeries", "series/displacement_error"),
        ("TextDocument", "summary"),
        *([("2D", "camera")] if with_frames else []),
    }
    rerun = Path(sys.executable).with_name("rerun")
    out = subprocess.run(
        [str(rerun), "rrd", "verify", str(path)],
        check=False,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 0, out.stderr


def test_mismatched_inputs_are_refused(case, tmp_path):
    c = case["comparison"]
    with pytest.raises(ValueError, match="q_sim must be"):
        rerun_log.write_rrd(
            tmp_path / "x.rrd", c, case["polys"], case["q_exp"], case["q_sim"][:-1], case["target"]
        )
    with pytest.raises(ValueError, match="pixel mapping"):
        rerun_log.write_rrd(
            tmp_path / "x.rrd",
            c,
            case["polys"],
            case["q_exp"],
            case["q_sim"],
            case["target"],
            frames=_frames(c),
        )


def test_speed_colours_share_one_scale_and_grey_out_nan():
    rgba = rerun_log.speed_colours(np.array([0.0, 1.0, 2.0, np.nan]), 0.0, 2.0)
    assert rgba.dtype == np.uint8 and rgba.shape == (4, 4)
    assert tuple(rgba[3]) == rerun_log.EXCLUDED_RGBA
    assert not np.array_equal(rgba[0], rgba[2])
    np.testing.assert_array_equal(rerun_log.speed_colours(np.array([5.0]), 0.0, 2.0), rgba[2:3])


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _bench_module():
    path = Path(__file__).parents[1] / "benchmarks" / "bench_rerun_view.py"
    spec = importlib.util.spec_from_file_location("bench_rerun_view", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_screenshot_check_needs_curves_not_only_legends():
    """The web-viewer check on a synthetic screenshot: a blank page draws nothing; in the
    target-energy view, the legend's red and blue dots alone are not curves, lines across the
    view are."""
    bench = _bench_module()
    h, w = 600, 1000
    page = np.full((h, w, 3), 248, np.uint8)
    assert not any(bench.view_content(page)["drawn"].values())
    r0, r1, c0, c1 = bench.view_regions(h, w)["target_ke"]
    for row, rgb in ((r1 - 20, (214, 39, 40)), (r1 - 8, (31, 119, 180))):  # legend dots
        page[row - 4 : row + 4, c0 + 10 : c0 + 18] = rgb
    page[r0 + 10 : r0 + 14, c0 + 30 : c1 - 30] = 40  # an axis-like dark line, not a curve
    report = bench.view_content(page)
    assert not report["drawn"]["target_ke"], report
    page[r0 + 30 : r0 + 32, c0 + 20 : c1 - 20] = (214, 39, 40)
    assert not bench.view_content(page)["drawn"]["target_ke"]  # the blue curve is missing
    page[r0 + 50 : r0 + 52, c0 + 20 : c1 - 20] = (31, 119, 180)
    report = bench.view_content(page)
    assert report["drawn"]["target_ke"], report
    assert [k for k, v in report["drawn"].items() if v] == ["target_ke"]


def test_web_viewer_draws_every_view_of_the_blueprint(case, tmp_path):
    """The .rrd in the Rerun web viewer (headless Chromium, WebGL on SwiftShader): every view of
    the blueprint is drawn (speed colours and magenta targets in both lattice views, the camera
    image, red and blue target-energy curves, the other curves and the summary), checked on the
    screenshot; blanking any one view's area of that screenshot makes exactly that view fail
    the check, so the check reads each view's own pixels."""
    bench = _bench_module()
    missing = bench.find_browser()[2]
    if missing:
        pytest.skip(f"browser test: {missing}")
    c = case["comparison"]
    path = rerun_log.write_rrd(
        tmp_path / "comparison.rrd",
        c,
        case["polys"],
        case["q_exp"],
        case["q_sim"],
        case["target"],
        frames=_frames(c),
        m_per_px=1e-3,
        origin_px=(20.0, 75.0),
    )
    # a 1000 x 640 window (not the benchmark's 1600 x 1000): SwiftShader draws every frame on
    # the CPU, so fewer pixels make the test faster; the view areas are fractions of the page
    report = bench.screenshot_rrd(
        path, tmp_path / "shot.png", web_port=_free_port(), window=(1000, 640)
    )
    assert report["started"] and not report["panic"], report
    assert report["title"] == "Rerun Viewer" and report["nonblank"], report
    assert all(report["drawn"].values()), report
    # negative controls on the same pixels: one view's area painted over with its background
    shot = np.asarray(Image.open(report["png"]).convert("RGB"))
    regions = bench.view_regions(*shot.shape[:2])
    assert set(regions) == set(report["drawn"])
    for name, (r0, r1, c0, c1) in regions.items():
        blank = shot.copy()
        blank[r0:r1, c0:c1] = np.median(shot[r0:r1, c0:c1].reshape(-1, 3), axis=0)
        drawn = bench.view_content(blank)["drawn"]
        assert [k for k, v in drawn.items() if not v] == [name], (name, drawn)
