"""Polygon geometry (metarig.polygon): hand-checked shoelace areas, centroids, inside tests."""

import numpy as np

from metarig.polygon import (area_centroids, first_overlap, points_inside, self_crossing,
                             self_crossings, self_intersecting, signed_areas)

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


def test_self_crossings_of_many_polygons_are_those_found_one_pair_at_a_time():
    """The batched check names, per polygon, the first crossing pair that a loop over the pairs
    (k, then m) finds, on random polygons of 4-8 vertices (many of them self-crossing)."""
    def first_pair(p):
        nv = len(p)
        for k in range(nv):
            for m in range(k + 2, nv):
                if (k, m) == (0, nv - 1):
                    continue
                a1, a2, b1, b2 = p[k], p[(k + 1) % nv], p[m], p[(m + 1) % nv]

                def orient(o, u, v):
                    return (u[0] - o[0]) * (v[1] - o[1]) - (u[1] - o[1]) * (v[0] - o[0])

                if (orient(b1, b2, a1) * orient(b1, b2, a2) < 0
                        and orient(a1, a2, b1) * orient(a1, a2, b2) < 0):
                    return (k, m)
        return None

    rng = np.random.default_rng(4)
    for nv in range(4, 9):
        polys = rng.uniform(-1.0, 1.0, size=(40, nv, 2))
        polys[0] = np.column_stack([np.cos(np.linspace(0, 2 * np.pi, nv, endpoint=False)),
                                    np.sin(np.linspace(0, 2 * np.pi, nv, endpoint=False))])
        expected = [first_pair(p) for p in polys]
        assert expected[0] is None and sum(e is not None for e in expected) >= 10
        got = self_crossings(polys)
        assert [None if k < 0 else (k, m) for k, m in got.tolist()] == expected
        assert [self_crossing(p) for p in polys] == expected


def test_points_inside_one_point_per_polygon_is_each_polygon_tested_alone():
    rng = np.random.default_rng(5)
    polys = rng.uniform(-1.0, 1.0, size=(50, 5, 2))
    polys[:, 2, 1] = polys[:, 1, 1]  # a horizontal edge in each
    pts = rng.uniform(-1.0, 1.0, size=(50, 2))
    alone = [bool(points_inside(x, y, poly)) for (x, y), poly in zip(pts, polys)]
    assert points_inside(pts[:, 0], pts[:, 1], polys).tolist() == alone
    assert 5 < sum(alone) < 45


def test_first_overlap_is_the_first_pair_a_loop_over_the_pairs_finds():
    """Squares of side 1 on a grid of pitch 1.5, one moved at a time: into its right
    neighbour (edges cross), wholly inside a neighbour's spot (containment, no crossing), or
    not at all."""
    grid = np.array([[i * 1.5, j * 1.5] for j in range(3) for i in range(3)])
    squares = grid[:, None, :] + SQUARE[None]
    assert first_overlap(squares) is None
    moved = squares.copy()
    moved[4] += [0.8, 0.3]  # unit 4 into unit 5
    assert first_overlap(moved) == (4, 5)
    moved = squares.copy()
    moved[7] = 0.5 * (SQUARE - 0.5) + grid[1] + 0.5
    assert first_overlap(moved) == (1, 7)
    moved[3] += [0.0, -1.2]  # unit 3 down into unit 0
    assert first_overlap(moved) == (0, 3)


def test_first_overlap_equals_every_pair_tested_on_random_polygons():
    """Random quadrilaterals (some far apart, some piled up): the swept screening finds the
    first overlapping pair that testing every pair in order finds, or none when none does."""
    from metarig.polygon import _overlapping

    rng = np.random.default_rng(6)
    found = 0
    for trial in range(30):
        n = int(rng.integers(2, 25))
        centres = rng.uniform(0.0, 3.0 + trial, size=(n, 1, 2))
        polys = centres + 0.5 * np.column_stack([np.cos(np.arange(4) * np.pi / 2),
                                                 np.sin(np.arange(4) * np.pi / 2)])[None]
        polys += rng.uniform(-0.1, 0.1, size=polys.shape)
        i, j = np.triu_indices(n, 1)
        every = np.flatnonzero(_overlapping(polys[i], polys[j]))
        expected = (int(i[every[0]]), int(j[every[0]])) if every.size else None
        assert first_overlap(polys) == expected
        found += expected is not None
    assert 5 < found < 30
