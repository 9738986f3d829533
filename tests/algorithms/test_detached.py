"""The detached-cluster detector against brute-force references, on synthetic and real data."""

from __future__ import annotations

from pathlib import Path

import laspy
import numpy as np
import pytest

from algorithms.detached import (
    detect_detached,
    envelope_scores,
    median_spacing,
    small_clusters,
)

AIRBORNE = Path(__file__).resolve().parents[1] / "data" / "airborne"


def slow_small_clusters(xyz: np.ndarray, link: float, max_cluster: int) -> np.ndarray:
    """Components of the full link graph by breadth-first search over explicit distances."""
    n = len(xyz)
    label = np.full(n, -1)
    current = 0
    for seed in range(n):
        if label[seed] >= 0:
            continue
        label[seed] = current
        queue = [seed]
        while queue:
            i = queue.pop()
            for j in range(n):
                if label[j] < 0 and np.sqrt(np.sum((xyz[i] - xyz[j]) ** 2)) <= link:
                    label[j] = current
                    queue.append(j)
        current += 1
    sizes = np.bincount(label)
    return sizes[label] <= max_cluster


def slow_envelope(xyz, candidate, k_surface, below, above):
    """One explicit least-squares plane per candidate (np.linalg.lstsq on the design matrix)."""
    surf = np.flatnonzero(~candidate)
    out = np.full(len(xyz), np.nan)
    for i in np.flatnonzero(candidate):
        d2 = np.sum((xyz[surf, :2] - xyz[i, :2]) ** 2, axis=1)
        nb = xyz[surf[np.argsort(d2, kind="stable")[:k_surface]]]
        c = nb.mean(axis=0)
        a_mat = np.c_[nb[:, 0] - c[0], nb[:, 1] - c[1], np.ones(len(nb))]
        coef = np.linalg.lstsq(a_mat, nb[:, 2] - c[2], rcond=None)[0]
        res = nb[:, 2] - c[2] - a_mat @ coef
        r = xyz[i, 2] - c[2] - np.array([xyz[i, 0] - c[0], xyz[i, 1] - c[1], 1.0]) @ coef
        out[i] = max((res.min() - r) / below, (r - res.max()) / above)
    return out


def rough_terrain(seed: int, n: int = 1500) -> np.ndarray:
    """A sloping, rough surface with a 3 m bump: real, never an outlier."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, 40, (n, 2))
    z = 0.3 * xy[:, 0] - 0.1 * xy[:, 1] + 3.0 * np.exp(-((xy - 20) ** 2).sum(1) / 20)
    return np.c_[xy, z + rng.normal(0, 0.15, n)]


def test_small_clusters_matches_full_graph_components():
    rng = np.random.default_rng(5)
    ground = rough_terrain(5, 300)
    clumps = np.vstack([c + rng.normal(0, 0.4, (m, 3)) for c, m in
                        (([10, 10, 30], 3), ([30, 5, -20], 8), ([5, 30, 50], 12))])
    xyz = np.vstack([ground, clumps])
    for link, max_cluster in ((1.0, 5), (3.0, 10), (3.0, 12), (0.5, 1)):
        np.testing.assert_array_equal(small_clusters(xyz, link, max_cluster),
                                      slow_small_clusters(xyz, link, max_cluster))


def test_envelope_matches_explicit_least_squares():
    xyz = rough_terrain(6, 400)
    candidate = np.zeros(len(xyz), bool)
    candidate[::17] = True
    fast = envelope_scores(xyz, candidate, k_surface=25, below=1.0, above=2.0)
    slow = slow_envelope(xyz, candidate, 25, 1.0, 2.0)
    np.testing.assert_allclose(fast, slow, rtol=1e-7, atol=1e-7)
    assert np.isnan(fast[~candidate]).all()


def test_floating_and_sunken_clumps_are_found_rough_surface_raises_nothing():
    rng = np.random.default_rng(7)
    ground = rough_terrain(7)
    high = np.array([12.0, 14.0, 35.0]) + rng.normal(0, 0.3, (4, 3))
    low = np.array([25.0, 8.0, -15.0]) + rng.normal(0, 0.3, (3, 3))
    xyz = np.vstack([ground, high, low])
    res = detect_detached(xyz)
    assert res.flagged[len(ground):].all()
    assert not res.flagged[:len(ground)].any()
    assert not detect_detached(ground).flagged.any()


def test_median_spacing_matches_explicit_distances():
    xyz = rough_terrain(9, 300)
    slow = np.median([np.sort(np.sqrt(((xyz - p) ** 2).sum(1)))[1] for p in xyz])
    assert median_spacing(xyz) == pytest.approx(slow, rel=1e-12)
    assert median_spacing(xyz[:1]) == 0.0


def test_sparse_cloud_keeps_its_small_objects():
    """1.6 m spacing (an ISPRS-like airborne cloud): a 6 m tree of 5 points is no outlier."""
    rng = np.random.default_rng(10)
    ground = rough_terrain(10, 600)  # 40 m x 40 m, ~1.6 m spacing
    tree = np.array([20.0, 20.0, 9.0]) + rng.normal(0, 0.5, (5, 3))
    res = detect_detached(np.vstack([ground, tree]))
    assert res.info["link_used"] > 3.0
    assert not res.flagged.any()
    far = detect_detached(np.vstack([ground, tree + [0, 0, 30]]))
    assert far.flagged[len(ground):].all() and not far.flagged[:len(ground)].any()


def test_results_unchanged_by_a_5e6_shift():
    xyz = np.vstack([rough_terrain(8), [[20.0, 20.0, 40.0]]])
    a = detect_detached(xyz)
    b = detect_detached(xyz + np.array([5e6, 5e6, 1e3]))
    np.testing.assert_array_equal(a.flagged, b.flagged)
    np.testing.assert_allclose(a.score, b.score, rtol=1e-6, atol=1e-6)


def test_bad_input_is_refused():
    with pytest.raises(ValueError, match="shape"):
        detect_detached(np.zeros((3, 2)))
    with pytest.raises(ValueError, match="link"):
        detect_detached(np.zeros((3, 3)), link=0)
    assert detect_detached(np.zeros((0, 3))).flagged.shape == (0,)


def test_real_airborne_gross_outliers():
    """laspy's append-bug tile (BSD-2): the targets, recall >= 95 %, false alarms <= 0.1 %."""
    las = laspy.read(AIRBORNE / "laspy__append-bug.laz")
    with np.load(AIRBORNE / "laspy__append-bug.truth.npz") as t:
        gross = t["gross"].astype(bool)
        unlabelled = ~t["is_outlier"].astype(bool)
    res = detect_detached(np.c_[las.x, las.y, las.z])
    assert res.flagged[gross].mean() >= 0.95
    assert res.flagged[unlabelled].mean() <= 0.001
