"""Tracker inputs: unit outline files and calibration JSON (validation, maps, homography)."""

import json

import cv2
import numpy as np
import pytest
from dic_synth import errors_px, make_scene

from metarig.polygon import area_centroids
from tracking.calibration import (
    Calibration,
    CalibrationError,
    calibration_from_dict,
    load_calibration,
)
from tracking.dic import DICTracker, init_state, track_frame
from tracking.units import UnitsError, load_unit_polygons, validate_polygons

SQUARE = [[0, 0], [2, 0], [2, 2], [0, 2]]


def test_centroid_is_the_area_centroid():
    # an L-shape: area centroid differs from the vertex mean
    ell = np.array([[[0, 0], [2, 0], [2, 1], [1, 1], [1, 2], [0, 2]]], float)
    np.testing.assert_allclose(area_centroids(ell), [[5 / 6, 5 / 6]])
    np.testing.assert_allclose(area_centroids(ell[:, ::-1]), [[5 / 6, 5 / 6]])


def test_units_file_plain_and_design(tmp_path):
    plain = tmp_path / "units.json"
    plain.write_text(json.dumps({"polygons_m": [SQUARE, SQUARE]}))
    assert load_unit_polygons(plain).shape == (2, 4, 2)
    design = tmp_path / "design.json"
    design.write_text(json.dumps({"scene": "x", "nx": 2, "polygons_m": [SQUARE], "other": 1}))
    assert load_unit_polygons(design).shape == (1, 4, 2)


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ({"units": []}, "no top-level key 'polygons_m'"),
        ({"polygons_m": [SQUARE, SQUARE[:3]]}, "ragged"),
        ({"polygons_m": [[[0, 0], [1, 1]]]}, "at least 3 vertices"),
        ({"polygons_m": [[[0, 0], [1, 0], [float("nan"), 1]]]}, "non-finite"),
        ({"polygons_m": [[[0, 0], [1, 1], [1, 0], [0, 1]]]}, "self-intersecting"),
        ({"polygons_m": [[[0, 0], [1, 1], [2, 2]]]}, "zero area"),
        ({"polygons_m": "nope"}, "non-empty list"),
    ],
)
def test_units_file_errors_name_the_file(tmp_path, content, message):
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(content))
    with pytest.raises(UnitsError, match=message) as info:
        load_unit_polygons(path)
    assert str(path) in str(info.value)


def test_units_file_unreadable(tmp_path):
    with pytest.raises(UnitsError, match="cannot read"):
        load_unit_polygons(tmp_path / "missing.json")
    (tmp_path / "x.json").write_text("{not json")
    with pytest.raises(UnitsError, match="not valid JSON"):
        load_unit_polygons(tmp_path / "x.json")
    with pytest.raises(UnitsError, match="unit 1"):
        validate_polygons([SQUARE, [[0, 0], [1, 1], [1, 0], [0, 1]]])


def test_calibration_round_trip_and_maps(tmp_path):
    d = {"fps": 500, "m_per_px": 2e-4, "origin_px": [10, 300], "y_up": True}
    path = tmp_path / "cal.json"
    path.write_text(json.dumps(d))
    cal = load_calibration(path)
    assert cal.fps == 500 and cal.origin_px == (10.0, 300.0)
    xy = np.array([[0.01, 0.02], [-0.003, 0.0]])
    px = cal.sample_to_px(xy)
    np.testing.assert_allclose(px[0], [10 + 50, 300 - 100])
    np.testing.assert_allclose(cal.px_to_sample(px), xy)
    down = calibration_from_dict({**d, "y_up": False})
    np.testing.assert_allclose(down.sample_to_px(xy)[0], [60, 400])
    assert calibration_from_dict(cal.to_json()) == cal


@pytest.mark.parametrize(
    ("patch", "message"),
    [
        ({"fps": 0}, "fps"),
        ({"fps": "fast"}, "'fps' must be a number"),
        ({"m_per_px": -1}, "m_per_px"),
        ({"origin_px": [1]}, "origin_px"),
        ({"y_up": "yes"}, "y_up"),
        ({"homography": [[1, 0], [0, 1]]}, "3x3"),
        ({"homography": [[0, 0, 0], [0, 0, 0], [0, 0, 0]]}, "invertible"),
    ],
)
def test_calibration_errors(tmp_path, patch, message):
    d = {"fps": 500, "m_per_px": 2e-4, "origin_px": [10, 300], "y_up": True, **patch}
    path = tmp_path / "cal.json"
    path.write_text(json.dumps(d))
    with pytest.raises(CalibrationError, match=message) as info:
        load_calibration(path)
    assert str(path) in str(info.value)


def test_calibration_missing_key_and_file(tmp_path):
    path = tmp_path / "cal.json"
    path.write_text(json.dumps({"m_per_px": 1e-3, "origin_px": [0, 0], "y_up": True}))
    with pytest.raises(CalibrationError, match="missing key 'fps'"):
        load_calibration(path)
    with pytest.raises(CalibrationError, match="cannot read"):
        load_calibration(tmp_path / "nope.json")
    text = json.dumps({"fps": 500, "m_per_px": 2e-4, "origin_px": [10, 300], "y_up": True})
    for data, message in ((text[:len(text) // 2].encode(), "not valid JSON"),  # cut short
                          (b"\xff\xfe\x00{", "not a text")):  # bytes that are not UTF-8
        path.write_bytes(data)
        with pytest.raises(CalibrationError, match=message) as info:
            load_calibration(path)
        assert str(path) in str(info.value) and "\n" not in str(info.value)


def test_tracking_through_a_homography():
    """A camera not square to the sample: frames are rectified by the calibration first."""
    scene = make_scene(3, 2)
    rng = np.random.default_rng(0)
    w, h = scene.cfg.width_px, scene.cfg.height_px
    square = np.float32([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]])
    raw = np.float32([[12, 5], [w - 3, 14], [w - 10, h - 2], [4, h - 12]])
    to_raw = cv2.getPerspectiveTransform(square, raw)
    big = 2  # a raw camera with finer pixels than the rectified grid keeps the warp harmless
    to_raw_big = np.diag([big, big, 1.0]) @ to_raw
    truth = np.tile(scene.px([1.3, -0.6, 0.04]), (scene.n, 1))
    rect_frames = [scene.render(np.zeros((scene.n, 3)), rng), scene.render(truth, rng)]
    up = [cv2.resize(f, None, fx=big, fy=big, interpolation=cv2.INTER_CUBIC)
          for f in rect_frames]
    raw_frames = [cv2.warpPerspective(f, to_raw_big @ np.diag([1 / big, 1 / big, 1]),
                                      (w * big, h * big), flags=cv2.INTER_CUBIC) for f in up]
    hom = np.linalg.inv(to_raw_big)
    cal = Calibration(fps=1000, m_per_px=scene.cfg.m_per_px, origin_px=scene.cfg.origin_px,
                      y_up=True, homography=tuple(map(tuple, hom)), rectified_size_px=(w, h))
    tr = DICTracker(scene.polygons_m, cal)
    st = init_state(tr, raw_frames[0])
    st, fp = track_frame(tr, st, raw_frames[1])
    assert not fp.lost.any()
    pos, rot = errors_px(scene, fp.q, truth)
    assert pos < 0.05 and rot < 2.0
