"""DROR and the low-intensity snow detector against per-point brute-force references."""

from __future__ import annotations

import numpy as np
import pytest

from algorithms.dror import detect_dror, dynamic_radius, neighbour_counts
from algorithms.snow import detect_snow


def slow_counts(xyz: np.ndarray, radius: np.ndarray) -> np.ndarray:
    """Other points within radius[i] of point i, one explicit distance at a time."""
    out = np.zeros(len(xyz), dtype=np.int64)
    for i in range(len(xyz)):
        dist = np.sqrt(np.sum((xyz - xyz[i]) ** 2, axis=1))
        out[i] = np.count_nonzero(dist <= radius[i]) - 1  # minus the point itself
    return out


def slow_radius(xyz, origin, multiplier, angular_resolution_deg, min_radius):
    out = np.empty(len(xyz))
    for i, p in enumerate(xyz):
        rng = np.sqrt(np.sum((p - np.asarray(origin)) ** 2))
        out[i] = max(min_radius, multiplier * rng * angular_resolution_deg * np.pi / 180.0)
    return out


def spinning_scene(seed: int, n_flakes: int = 60):
    """Rings of a 32-channel sensor on a ground plane and a wall, plus isolated dark flakes."""
    rng = np.random.default_rng(seed)
    az = np.deg2rad(np.arange(0.0, 360.0, 0.2))
    pts = []
    for elev in np.deg2rad(np.linspace(-25, -2, 16)):  # rings hitting the ground at z = -1.8
        r = 1.8 / np.tan(-elev)
        pts.append(np.c_[r * np.cos(az), r * np.sin(az), np.full(az.size, -1.8)])
    for h in np.linspace(-1.5, 3.0, 16):  # rings hitting a cylinder wall at 15 m
        pts.append(np.c_[15 * np.cos(az), 15 * np.sin(az), np.full(az.size, h)])
    surface = np.vstack(pts) + rng.normal(0, 0.005, (sum(len(p) for p in pts), 3))
    flakes = rng.uniform(-6, 6, (n_flakes, 3)) + np.array([0, 0, 1.0])
    flakes = flakes[np.linalg.norm(flakes, axis=1) > 2.0]
    xyz = np.vstack([surface, flakes])
    intensity = np.r_[rng.integers(1, 255, len(surface)), np.zeros(len(flakes), dtype=int)]
    truth = np.r_[np.zeros(len(surface), bool), np.ones(len(flakes), bool)]
    return xyz, intensity, truth


def test_counts_and_radius_match_slow_reference():
    rng = np.random.default_rng(1)
    xyz = np.vstack([rng.normal(0, 2, (300, 3)), rng.normal(0, 2, (5, 3))])
    xyz[-5:] = xyz[:5]  # exact duplicates count as neighbours
    origin = (0.5, -1.0, 0.2)
    radius = dynamic_radius(xyz, origin, multiplier=4, angular_resolution=2.0, min_radius=0.1)
    np.testing.assert_allclose(radius, slow_radius(xyz, origin, 4, 2.0, 0.1), rtol=1e-12)
    slow = slow_counts(xyz, radius)
    for cap in (1, 2, 5, 400):
        np.testing.assert_array_equal(neighbour_counts(xyz, radius, cap), np.minimum(slow, cap))
    some = np.arange(0, len(xyz), 7)
    np.testing.assert_array_equal(neighbour_counts(xyz, radius[some], 3, queries=some),
                                  np.minimum(slow[some], 3))


def test_dror_flags_exactly_the_points_with_too_few_neighbours():
    rng = np.random.default_rng(2)
    xyz = rng.uniform(-10, 10, (400, 3))
    res = detect_dror(xyz, multiplier=4, angular_resolution=1.0, k_min=2)
    counts = slow_counts(xyz, slow_radius(xyz, (0, 0, 0), 4, 1.0, 0.04))
    np.testing.assert_array_equal(res.flagged, counts < 2)
    np.testing.assert_array_equal(res.score, 2 - np.minimum(counts, 2))
    assert res.critical_value == 0.0


def test_snow_is_dror_restricted_to_dark_points():
    xyz, intensity, _ = spinning_scene(3)
    xyz, intensity = xyz[::20], intensity[::20]  # small enough for the O(n^2) reference
    intensity[::3] = 0  # some dark surface points too
    res = detect_snow(xyz, intensity, k_min=4)
    counts = slow_counts(xyz, slow_radius(xyz, (0, 0, 0), 4, 0.2, 0.04))
    dark = intensity <= 0
    np.testing.assert_array_equal(res.flagged, dark & (counts < 4))
    assert np.all(np.isnan(res.score[~dark]))
    np.testing.assert_array_equal(res.score[dark], 4 - np.minimum(counts[dark], 4))


def test_flakes_found_and_clean_surfaces_kept():
    xyz, intensity, truth = spinning_scene(4)
    snow = detect_snow(xyz, intensity)
    assert snow.flagged[truth].all()
    assert not snow.flagged[~truth].any()
    dror = detect_dror(xyz)
    assert dror.flagged[truth].mean() > 0.9
    # The sensor origin matters: moved 40 m away, every range and radius grows.
    far = detect_dror(xyz, origin=(40.0, 0.0, 0.0))
    assert far.flagged[truth].sum() < dror.flagged[truth].sum()


def test_bad_input_is_refused():
    with pytest.raises(ValueError, match="shape"):
        detect_dror(np.zeros((4, 2)))
    with pytest.raises(ValueError, match="NaN"):
        detect_dror(np.array([[0.0, 0.0, np.nan]]))
    with pytest.raises(ValueError, match="k_min"):
        detect_dror(np.zeros((4, 3)), k_min=0)
    with pytest.raises(ValueError, match="intensity"):
        detect_snow(np.zeros((4, 3)), np.zeros(3))


def test_empty_cloud():
    assert detect_dror(np.zeros((0, 3))).flagged.shape == (0,)
    assert detect_snow(np.zeros((0, 3)), np.zeros(0)).flagged.shape == (0,)
