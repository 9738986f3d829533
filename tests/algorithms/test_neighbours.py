"""Nearest-neighbour queries asked cell by cell: the k-d tree's answers, in the queries' order."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from algorithms.neighbours import (
    ORDERED_QUERIES_MIN,
    any_near_apart,
    neighbour_tree,
    query_nearest,
    space_order,
)


def _cloud(n: int, seed: int = 3) -> np.ndarray:
    """A survey-like cloud: a sloping street on a millimetre grid (ties are common) with a
    few points floating above it, in a shuffled (not spatial) order."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0.0, [80.0, 12.0], size=(n, 2))
    z = 0.02 * xy[:, 0] + rng.normal(0.0, 0.005, n)
    z[rng.random(n) < 0.01] += rng.uniform(0.5, 3.0)
    return np.round(np.column_stack([xy, z]), 3)


@pytest.mark.parametrize("k", [1, 9, [9]])
def test_query_nearest_gives_the_plain_query_in_the_queries_order(k: int | list[int]) -> None:
    xyz = _cloud(ORDERED_QUERIES_MIN + 5_000)
    queries = xyz[::-1]  # another order than the tree's points
    want_d, want_i = cKDTree(xyz).query(queries, k=k)
    got_d, got_i = query_nearest(neighbour_tree(xyz), queries, k)
    assert got_d.shape == want_d.shape and got_i.shape == want_i.shape
    np.testing.assert_array_equal(got_d, want_d)
    # the same points wherever the distance decides (tied points may come in another order)
    kmax = max(np.atleast_1d(k))
    around, _ = cKDTree(xyz).query(queries, k=kmax + 1)
    untied = np.all(np.diff(around.reshape(len(queries), -1), axis=1) > 0, axis=1)
    assert untied.mean() > 0.2
    np.testing.assert_array_equal(np.asarray(got_i)[untied], np.asarray(want_i)[untied])


def test_query_nearest_with_an_upper_bound_marks_the_missing_alike() -> None:
    xyz = _cloud(ORDERED_QUERIES_MIN + 1_000, seed=5)
    want_d, want_i = cKDTree(xyz).query(xyz, k=4, distance_upper_bound=0.05)
    got_d, got_i = query_nearest(neighbour_tree(xyz), xyz, 4, distance_upper_bound=0.05)
    np.testing.assert_array_equal(got_d, want_d)
    missing = ~np.isfinite(want_d)
    assert missing.any() and (~missing).any()
    assert np.all(got_i[missing] == len(xyz))


def test_space_order_is_a_permutation_grouping_cells() -> None:
    xyz = _cloud(20_000, seed=7)
    order = space_order(xyz)
    assert np.array_equal(np.sort(order), np.arange(len(xyz)))
    cells = np.floor(xyz[order, :2])
    # each cell's points come together: a cell's key never reappears after another cell's
    key = cells[:, 0] * 1e6 + cells[:, 1]
    changes = np.count_nonzero(np.diff(key) != 0) + 1
    assert changes == len(np.unique(key))


def test_small_query_sets_are_asked_as_they_come() -> None:
    xyz = _cloud(2_000, seed=9)
    want = cKDTree(xyz).query(xyz[:100], k=5)
    got = query_nearest(neighbour_tree(xyz), xyz[:100], 5)
    np.testing.assert_array_equal(got[0], want[0])


def test_any_near_apart_is_the_numpy_expression():
    rng = np.random.default_rng(3)
    m, k = 2000, 7
    values = np.round(rng.uniform(0, 5, m), 1)  # ties at the bound, exactly
    values[::97] = np.nan
    idx = rng.integers(0, m, (m, k))
    near = rng.random((m, k)) < 0.4
    slow = np.any(near & (np.abs(values[idx] - values[:, None]) >= 0.5), axis=1)
    fast = any_near_apart(values, idx, near, 0.5)
    np.testing.assert_array_equal(fast, slow)
    assert slow.any() and not slow.all()
