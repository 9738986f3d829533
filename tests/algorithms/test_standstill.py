"""standstill: a profile scanner that stops, against a loop over the windows."""

from __future__ import annotations

import numpy as np
import pytest

from algorithms.errors import ParameterError
from algorithms.standstill import merged_spans, still_spans


def corridor_survey(rng: np.random.Generator, stop: tuple[float, float] = (1.0, 2.0),
                    speed: float = 1.0, end: float = 3.0):
    """A profile scanner 1.5 m up turning at 50.37 Hz (20 kHz pulses, 0.9 degrees apart, the
    phase drifting from turn to turn) in the y-z plane inside a corridor (floor z = 0, walls
    y = +-5, ceiling z = 6), driving along x at ``speed`` except during ``stop``:
    (gps_time, xyz)."""
    t = np.arange(0.0, end, 1 / 20_000)
    moving = np.clip(t, None, stop[0]) + np.clip(t - stop[1], 0, None)
    x = speed * moving
    theta = 2 * np.pi * 50.37 * t
    dy, dz = np.cos(theta), np.sin(theta)
    with np.errstate(divide="ignore"):
        to_wall = np.where(dy != 0, 5.0 / np.abs(dy), np.inf)
        to_floor = np.where(dz < 0, 1.5 / -dz, np.inf)
        to_ceiling = np.where(dz > 0, 4.5 / dz, np.inf)
    r = np.minimum(to_wall, np.minimum(to_floor, to_ceiling))
    xyz = np.column_stack([x, r * dy, 1.5 + r * dz]) + rng.normal(0, 0.002, (len(t), 3))
    return t, xyz


def slow_spans(t, xyz, window, lag, tolerance):
    """Every window pair with all pairwise distances and an explicit projection onto the line
    through the two nearest; the sample is every point."""
    which = np.floor((t - t.min()) / window).astype(int)
    spans = []
    for i in range(which.max() + 1 - lag):
        a, b = xyz[which == i], xyz[which == i + lag]
        if min(len(a), len(b)) < 20:
            continue
        distances = []
        for p in a:
            q1, q2 = b[np.argsort(np.linalg.norm(b - p, axis=1), kind="stable")[:2]]
            u = (q2 - q1) / np.linalg.norm(q2 - q1)
            distances.append(np.linalg.norm((np.eye(3) - np.outer(u, u)) @ (p - q1)))
        if np.median(distances) <= tolerance:
            spans.append((t.min() + i * window, t.min() + (i + lag + 1) * window))
    return merged_spans(np.array(spans).reshape(-1, 2))


def test_the_stop_of_a_profile_scanner_is_found():
    t, xyz = corridor_survey(np.random.default_rng(0))
    spans = still_spans(t, xyz)
    assert spans.shape == (1, 2)
    start, end = spans[0]
    assert 0.9 <= start <= 1.1 and 1.9 <= end <= 2.1


def test_a_creeping_vehicle_is_not_still():
    t, xyz = corridor_survey(np.random.default_rng(1), stop=(5.0, 5.0), speed=0.05, end=2.0)
    assert still_spans(t, xyz).shape == (0, 2)


def test_still_spans_equal_a_loop_over_the_windows():
    rng = np.random.default_rng(2)
    t, xyz = corridor_survey(rng, stop=(0.3, 0.8), end=1.2)
    keep = np.sort(rng.choice(len(t), 3000, replace=False))
    t, xyz = t[keep], xyz[keep]
    for tolerance in (0.005, 0.02, 0.05):
        got = still_spans(t, xyz, window=0.1, lag=2, tolerance=tolerance, sample=10**6)
        np.testing.assert_array_equal(got, slow_spans(t, xyz, 0.1, 2, tolerance))
    assert len(still_spans(t, xyz, window=0.1, lag=2, tolerance=0.05)) > 0


def test_order_and_untimed_points_do_not_matter():
    t, xyz = corridor_survey(np.random.default_rng(3), end=2.5)
    want = still_spans(t, xyz)
    shuffled = np.random.default_rng(4).permutation(len(t))
    t2, xyz2 = t[shuffled].copy(), xyz[shuffled]
    t2[:50] = np.nan
    got = still_spans(t2, xyz2)
    np.testing.assert_allclose(got, want, atol=0.1)
    assert still_spans(np.full(3, np.nan), np.zeros((3, 3))).shape == (0, 2)


def test_merged_spans_joins_what_overlaps():
    spans = np.array([[3.0, 4.0], [0.0, 1.0], [0.5, 2.0], [2.0, 2.5], [5.0, 6.0]])
    np.testing.assert_array_equal(merged_spans(spans), [[0.0, 2.5], [3.0, 4.0], [5.0, 6.0]])


def test_bad_parameters():
    t, xyz = corridor_survey(np.random.default_rng(5), end=0.5)
    with pytest.raises(ParameterError):
        still_spans(t, xyz, window=0)
    with pytest.raises(ParameterError):
        still_spans(t[:-1], xyz)
