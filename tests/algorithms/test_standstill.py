"""standstill: a profile scanner that stops, against a loop over the windows."""

from __future__ import annotations

import numpy as np
import pytest

from algorithms.errors import ParameterError
from algorithms.standstill import (
    LAG,
    PIECE_WINDOWS,
    merged_spans,
    piece_flags,
    profile_starts,
    still_members,
    still_spans,
    stop_flags,
    stop_origin,
    stream_stop_flags,
    window_ids,
)
from tests.lasfiles import corridor_survey


def slow_spans(t, xyz, window, lag, tolerance):
    """Every window pair with all pairwise distances and an explicit projection onto the line
    through the two nearest; the sample is every point."""
    which = np.floor(t / window).astype(int)
    spans = []
    for i in range(which.min(), which.max() + 1 - lag):
        a, b = xyz[which == i], xyz[which == i + lag]
        if min(len(a), len(b)) < 20:
            continue
        distances = []
        for p in a:
            q1, q2 = b[np.argsort(np.linalg.norm(b - p, axis=1), kind="stable")[:2]]
            u = (q2 - q1) / np.linalg.norm(q2 - q1)
            distances.append(np.linalg.norm((np.eye(3) - np.outer(u, u)) @ (p - q1)))
        if np.median(distances) <= tolerance:
            spans.append((i * window, (i + lag + 1) * window))
    return merged_spans(np.array(spans).reshape(-1, 2))


def test_the_stop_of_a_profile_scanner_is_found():
    t, xyz, _ = corridor_survey(np.random.default_rng(0))
    spans = still_spans(t, xyz)
    assert spans.shape == (1, 2)
    start, end = spans[0]
    assert 0.9 <= start <= 1.1 and 1.9 <= end <= 2.1


def test_a_creeping_vehicle_is_not_still():
    t, xyz, _ = corridor_survey(np.random.default_rng(1), stop=(5.0, 5.0), speed=0.05, end=2.0)
    assert still_spans(t, xyz).shape == (0, 2)


def test_still_spans_equal_a_loop_over_the_windows():
    rng = np.random.default_rng(2)
    t, xyz, _ = corridor_survey(rng, stop=(0.3, 0.8), end=1.2)
    keep = np.sort(rng.choice(len(t), 3000, replace=False))
    t, xyz = t[keep], xyz[keep]
    for tolerance in (0.005, 0.02, 0.05):
        got = still_spans(t, xyz, window=0.1, lag=2, tolerance=tolerance, sample=10**6)
        np.testing.assert_array_equal(got, slow_spans(t, xyz, 0.1, 2, tolerance))
    assert len(still_spans(t, xyz, window=0.1, lag=2, tolerance=0.05)) > 0


def test_order_and_untimed_points_do_not_matter():
    t, xyz, _ = corridor_survey(np.random.default_rng(3), end=2.5)
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
    t, xyz, _ = corridor_survey(np.random.default_rng(5), end=0.5)
    with pytest.raises(ParameterError):
        still_spans(t, xyz, window=0)
    with pytest.raises(ParameterError):
        still_spans(t[:-1], xyz)


# --- free space at a stop -------------------------------------------------------------------

def exhaust_at_a_stop(seed: int = 11):
    """:func:`corridor_survey` standing 1.8 s (three pieces of GPS seconds) in exhaust."""
    t, xyz, droplet = corridor_survey(np.random.default_rng(seed), stop=(0.75, 2.55), end=3.3,
                                      plume=0.3)
    return t + 1000.0, xyz, droplet


def test_exhaust_at_a_stop_is_flagged_and_the_corridor_is_not():
    t, xyz, droplet = exhaust_at_a_stop()
    flags, info = stop_flags(t, np.ones(len(t), int), xyz)
    assert info["stop_pieces"] == 3 and info["stop_pieces_placed"] == 3
    assert np.count_nonzero(flags & droplet) >= 0.5 * droplet.sum()
    assert not np.any(flags & ~droplet)


def test_a_scanner_that_never_stops_flags_nothing():
    t, xyz, _ = corridor_survey(np.random.default_rng(6), stop=(9.0, 9.0), end=2.0)
    flags, info = stop_flags(t + 1000.0, np.ones(len(t), int), xyz)
    assert not flags.any() and info["stop_pieces"] == 0


def test_streamed_in_chunks_equals_the_run_in_memory_and_needs_time_order():
    t, xyz, _ = exhaust_at_a_stop()
    rng = np.random.default_rng(7)
    # a second scanner interleaved with the first: each one's returns stay in time order
    source = rng.integers(1, 3, len(t))
    want, info = stop_flags(t, source, xyz)
    assert want.any()
    got = np.zeros(len(t), dtype=bool)

    def mark(rows):
        got[rows] = True

    streamed = stream_stop_flags(t, source, np.ones(len(t), bool), tuple(xyz.T), mark,
                                 chunk=7_001)
    assert streamed == info
    np.testing.assert_array_equal(got, want)
    shuffled = rng.permutation(len(t))
    assert stream_stop_flags(t[shuffled], source[shuffled], np.ones(len(t), bool),
                             tuple(xyz[shuffled].T), mark, chunk=7_001) is None
    flags, _ = stop_flags(t[shuffled], source[shuffled], xyz[shuffled])
    np.testing.assert_array_equal(flags, want[shuffled])


def test_a_piece_needs_only_its_windows_and_lag_windows_around_it():
    t, xyz, _ = exhaust_at_a_stop()
    which = window_ids(t)
    piece = 1001
    full, _ = piece_flags(which, xyz, t, piece)
    lo, hi = np.searchsorted(which, [piece * PIECE_WINDOWS - LAG,
                                     (piece + 1) * PIECE_WINDOWS + LAG])
    part, _ = piece_flags(which[lo:hi], xyz[lo:hi], t[lo:hi], piece)
    assert full.any()
    np.testing.assert_array_equal(full[lo:hi], part)
    assert not full[:lo].any() and not full[hi:].any()


def test_still_members_equal_a_loop_over_the_spans():
    rng = np.random.default_rng(8)
    which = np.sort(rng.integers(0, 60, 500))
    still = np.unique(rng.integers(0, 60, 7))
    want = [any(i <= j <= i + LAG for i in still) for j in which]
    np.testing.assert_array_equal(still_members(which, still), want)


def rotated(xyz: np.ndarray) -> np.ndarray:
    """The points turned 50 degrees about z and 20 about x and moved: an oblique scan plane
    far from the origin."""
    a, b = np.deg2rad(50), np.deg2rad(20)
    rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    rx = np.array([[1, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]])
    return xyz @ (rz @ rx).T + [305.0, -73.0, 42.0]


def test_a_still_scanners_position_is_fitted_from_its_points_in_any_orientation():
    t, xyz, _ = exhaust_at_a_stop()
    second = (t >= 1001.0) & (t < 1002.0)
    points, truth = rotated(xyz[second]), rotated(np.array([[0.75, 0.0, 1.5]]))[0]
    origin, info = stop_origin(points, t[second])
    assert origin is not None, info
    assert np.linalg.norm(origin - truth) < 0.005
    starts = profile_starts(points, t[second])
    assert starts and np.linalg.norm(starts[0] - truth) < 0.5


def test_a_standing_multi_beam_head_is_not_taken_for_a_profile_scanner():
    """Sixteen cones of a spinning head at a stop: still, but no plane through the scanner;
    no position, nothing flagged."""
    t = 1000.0 + np.arange(0.0, 1.0, 1 / 20_000)
    azimuth = 2 * np.pi * 10.0 * t
    elevation = np.deg2rad(np.linspace(-15, 15, 16))[np.arange(len(t)) % 16]
    r = np.minimum(1.8 / np.maximum(-np.sin(elevation), 1e-3), 12.0)
    xyz = np.column_stack([r * np.cos(elevation) * np.cos(azimuth),
                           r * np.cos(elevation) * np.sin(azimuth), 1.8 + r * np.sin(elevation)])
    xyz += np.random.default_rng(9).normal(0, 0.002, xyz.shape)
    origin, info = stop_origin(xyz, t)
    assert origin is None and "plane" in info["reason"]
    flags, info = stop_flags(t, np.ones(len(t), int), xyz)
    assert not flags.any() and info["stop_pieces_placed"] == 0


def test_a_stop_whose_beams_miss_their_returns_by_milliradians_is_not_placed():
    """At a stop nothing but the returns' noise moves a beam: a position whose beams miss
    their returns by 5 mrad (median) is refused, one within 0.3 mrad is kept."""
    t, xyz, _ = exhaust_at_a_stop()
    second = (t >= 1001.0) & (t < 1002.0)
    rel = xyz[second] - [0.75, 0.0, 1.5]  # from the scanner, in its y-z plane
    rng = np.random.default_rng(10)
    for jitter, placed in ((0.0003, True), (0.008, False)):
        turn = rng.normal(0, jitter, len(rel))
        c, s = np.cos(turn), np.sin(turn)
        moved = np.column_stack([rel[:, 0], c * rel[:, 1] - s * rel[:, 2],
                                 s * rel[:, 1] + c * rel[:, 2]]) + [0.75, 0.0, 1.5]
        origin, info = stop_origin(moved, t[second])
        assert (origin is not None) == placed, info
