"""Polygon geometry (metarig.polygon): hand-checked shoelace areas, centroids, inside tests."""

import numpy as np

from metarig.polygon import area_centroids, points_inside, self_intersecting, signed_areas

SQUARE = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])  # CCW, area 1
TRIANGLE = np.array([[0.0, 0.0], [3.0, 0.0], [0.0, 6.0]])  # CCW, area 9, centroid (1, 2)


def test_unit_square():
    assert signed_areas(SQUARE) == 1.0
    np.testing.assert_allclose(area_centroids(SQUARE), [0.5, 0.5])


def test_triangle():
    assert signed_areas(TRIANGLE) == 9.0
    np.testing.assert_allclose(area_centroids(TRIANGLE), [1.0, 2.0])


def test_orientation_sign_and_batching():
    polys = np.stack([SQUARE + [2.0, -1.0], SQUARE[::-1] * 2.0])  # shifted CCW; scaled CW
    np.testing.assert_allclose(signed_areas(polys), [1.0, -4.0])
    # the centroid does not depend on the orientation
    np.testing.assert_allclose(area_centroids(polys), [[2.5, -0.5], [1.0, 1.0]])
    assert area_centroids(polys[None]).shape == (1, 2, 2)


def test_area_centroid_is_not_the_vertex_mean():
    # square [0, 2]^2 (area 4 at (1, 1)) + triangle (2,0) (4,0) (2,2) (area 2 at (8/3, 2/3));
    # the vertex mean would be (1.5, 1)
    trap = np.array([[0.0, 0.0], [4.0, 0.0], [2.0, 2.0], [0.0, 2.0]])
    assert signed_areas(trap) == 6.0
    np.testing.assert_allclose(area_centroids(trap), [14 / 9, 8 / 9])


def test_points_inside_points_and_grid():
    x = np.array([0.5, 1.5, 0.25, -0.1])
    y = np.array([0.5, 0.5, 0.9, 0.5])
    np.testing.assert_array_equal(points_inside(x, y, SQUARE), [True, False, True, False])
    # the triangle's hypotenuse is x = 3 - y / 2
    grid = points_inside(np.array([0.5, 2.8])[None, :], np.array([0.5, 0.1, 3.0, 7.0])[:, None],
                         TRIANGLE)  # [rows, cols]
    np.testing.assert_array_equal(grid, [[True, False], [True, True], [True, False],
                                         [False, False]])


def test_self_intersecting():
    bowtie = np.array([[0.0, 0.0], [1.0, 1.0], [1.0, 0.0], [0.0, 1.0]])
    assert self_intersecting(bowtie) and not self_intersecting(SQUARE)
    assert not self_intersecting(TRIANGLE)
