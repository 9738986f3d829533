"""The TIN triangulators against scipy's Qhull, and the neighbour map against a brute-force one."""

from __future__ import annotations

import numpy as np
import pytest
import startinpy  # noqa: F401 - a required dependency: its absence is an error, not a skip

from algorithms.tin import delaunay, edge_neighbours, morton_order


def triangle_set(tri: np.ndarray) -> set[tuple[int, ...]]:
    return {tuple(sorted(int(v) for v in t)) for t in tri}


def slow_neighbours(tri: np.ndarray) -> np.ndarray:
    """nbr[t, k] by comparing every pair of triangles: the one sharing the edge opposite k."""
    nbr = np.full(tri.shape, -1)
    for t in range(len(tri)):
        for k in range(3):
            edge = {int(tri[t, (k + 1) % 3]), int(tri[t, (k + 2) % 3])}
            for u in range(len(tri)):
                if u != t and edge <= set(int(v) for v in tri[u]):
                    nbr[t, k] = u
    return nbr


@pytest.mark.parametrize("seed", range(3))
def test_startin_gives_qhulls_triangles_in_the_callers_numbering(seed):
    rng = np.random.default_rng(seed)
    xy = rng.random((500, 2)) * [80.0, 30.0] + [5e5, 5e6]  # UTM-sized, as the filter never is
    xy -= xy.mean(axis=0)
    a, _, name_a = delaunay(xy, backend="startin")
    b, _, name_b = delaunay(xy, backend="qhull")
    assert (name_a, name_b) == ("startin", "qhull")
    assert triangle_set(a) == triangle_set(b)


def test_auto_prefers_startin():
    xy = np.random.default_rng(4).random((50, 2))
    assert delaunay(xy)[2] == "startin"


def test_points_closer_than_a_millimetre_all_become_vertices():
    # LAS files with 0.1 mm scales: startin's default 1 mm snapping would drop points.
    rng = np.random.default_rng(5)
    xy = np.round(rng.random((400, 2)) * 0.05, 4)
    xy = np.unique(xy, axis=0)
    tri, _, name = delaunay(xy, backend="startin")
    assert name == "startin"
    assert np.unique(tri).size == len(xy)


@pytest.mark.parametrize("seed", range(3))
def test_edge_neighbours_match_brute_force(seed):
    xy = np.random.default_rng(seed).random((60, 2))
    tri, nbr_qhull, _ = delaunay(xy, backend="qhull")
    expected = slow_neighbours(tri)
    np.testing.assert_array_equal(edge_neighbours(tri, len(xy)), expected)
    np.testing.assert_array_equal(nbr_qhull, expected)  # Qhull's convention is the same


def test_collinear_points_give_no_triangles():
    xy = np.column_stack([np.arange(10.0), 2 * np.arange(10.0)])
    tri, nbr, name = delaunay(xy)
    assert tri.shape == (0, 3) and nbr.shape == (0, 3) and name == "none"


def test_morton_order_is_a_permutation_that_keeps_quadrants_together():
    xy = np.array([[0.9, 0.9], [0.1, 0.1], [0.9, 0.1], [0.1, 0.9], [0.2, 0.2]])
    order = morton_order(xy)
    assert sorted(order.tolist()) == list(range(5))
    assert order.tolist()[:2] == [1, 4]  # the lower-left quadrant comes first
