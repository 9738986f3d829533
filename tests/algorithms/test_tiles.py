"""The spatial helpers of algorithms.tiles against brute force."""

from __future__ import annotations

import numpy as np
import pytest

from algorithms.tiles import cell_counts, kth_distance_within


def brute_kth(points: np.ndarray, k: int) -> np.ndarray:
    """Each point's distance to its k-th nearest point, itself first, from every pair."""
    d = np.linalg.norm(points[:, None, :] - points[None, :, :], axis=2)
    return np.sort(d, axis=1)[:, k - 1]


def clustered(rng: np.random.Generator, n: int, d: int) -> np.ndarray:
    """A dense clump, a sparse scatter and a few far points."""
    dense = rng.normal(0.0, 0.3, (n // 2, d))
    sparse = rng.uniform(-5.0, 5.0, (n - n // 2 - 3, d))
    far = rng.uniform(20.0, 30.0, (3, d))
    return np.vstack([dense, sparse, far])


@pytest.mark.parametrize("d", [2, 3])
def test_cell_counts_match_counting_each_cell(d: int) -> None:
    rng = np.random.default_rng(d)
    points = clustered(rng, 300, d)
    edge = 0.7
    ij = np.floor((points - points.min(axis=0)) / edge).astype(int)
    expected = [(ij == row).all(axis=1).sum() for row in ij]
    assert cell_counts(points, edge).tolist() == expected


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("limit", [0.4, 1.5, 40.0])
def test_kth_distance_within_is_exact_or_a_bound_within_allowed(d: int, limit: float) -> None:
    rng = np.random.default_rng(int(10 * limit) + d)
    points = clustered(rng, 400, d)
    k = 9
    where = rng.random(len(points)) < 0.8
    allowed = np.where(rng.random(len(points)) < 0.7, limit, limit / 3)
    truth = brute_kth(points, k)
    got = kth_distance_within(points, k, where, allowed)
    assert np.all(got[~where] == 0.0)
    exact = np.isclose(got, truth, rtol=1e-12, atol=1e-12)
    bounded = where & ~exact
    if limit >= 1.5:  # the dense clump's cells hold k points: the shortcut is taken
        assert bounded.any()
    assert np.all(got[bounded] >= truth[bounded])  # a bound never hides a longer reach
    assert np.all(got[bounded] <= allowed[bounded])  # and only where it is harmless
    # wherever the true reach exceeds what is allowed, the exact value is reported
    over = where & (truth > allowed)
    assert np.allclose(got[over], truth[over])
    without = kth_distance_within(points, k, where)
    assert np.allclose(without[where], truth[where])


def test_kth_distance_within_too_few_points_is_unbounded() -> None:
    points = np.zeros((3, 3))
    where = np.array([True, False, True])
    got = kth_distance_within(points, 5, where, np.full(3, 1.0))
    assert got.tolist() == [np.inf, 0.0, np.inf]
