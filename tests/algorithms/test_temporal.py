"""Tests of the temporal detector (paper's algorithm (a), eqs. 1-17).

The fast kernels are compared with ``slow_standardised_difference``, a per-point loop that
writes eqs. 11, 14, 15, 16 and 17 literally with an explicit 3x3 matrix and ``np.linalg.inv``.
"""

from __future__ import annotations

import json
from pathlib import Path

import laspy
import numpy as np
import pytest

from algorithms.errors import MissingDimensionError, NotTimeOrderedError, ParameterError
from algorithms.stats import normal_critical_value
from algorithms.temporal import TemporalStream, detect_temporal, windows
from algorithms.temporal.segments import cut_segments, segment_windows
from algorithms.temporal.windows import segment_differences, window_bounds, window_differences
from tests.lasfiles import write_las

# --------------------------------------------------------------------------------------------
# Slow reference, written from the paper's equations
# --------------------------------------------------------------------------------------------


def slow_window(k: int, seg_start: int, seg_end: int, n1: int, n2: int) -> range:
    """Rows of point k's window: [k - n1, k + n2], shifted to stay inside its segment."""
    size = n1 + n2 + 1
    if seg_end - seg_start < size:
        return range(seg_start, seg_end)
    start = k - n1
    if start < seg_start:
        start = seg_start
    if start + size > seg_end:
        start = seg_end - size
    return range(start, start + size)


def slow_standardised_difference(
    t: np.ndarray, z: np.ndarray, sigma: np.ndarray, k: int, rows: range
) -> float:
    """Eq. 17 for point k from the window ``rows``, every equation written out literally."""
    rows = list(rows)
    # Eq. 14: the 3x3 matrix of weighted moments of delta = t_{k+i} - t_k, inverted.
    m = np.zeros((3, 3))
    for r in rows:
        d = t[r] - t[k]
        m += (1.0 / sigma[r] ** 2) * np.array(
            [[1, d, d**2], [d, d**2, d**3], [d**2, d**3, d**4]]
        )
    inv = np.linalg.inv(m)
    lam1, lam2, lam3 = inv[0, 0], inv[1, 0], inv[2, 0]
    # Eq. 11: a_i(k).
    a = {}
    for r in rows:
        d = t[r] - t[k]
        a[r] = (1.0 / sigma[r] ** 2) * (lam1 + lam2 * d + lam3 * d**2)
    # Eq. 15: prediction from the neighbours.
    z_p = sum(a[r] * z[r] for r in rows if r != k) / (1.0 - a[k])
    # Eq. 16: variance of the difference.
    var = sigma[k] ** 2 + sum(a[r] ** 2 * sigma[r] ** 2 for r in rows if r != k) / (
        1.0 - a[k]
    ) ** 2
    # Eq. 17.
    return (z[k] - z_p) / np.sqrt(var)


def slow_detect(
    xyz: np.ndarray,
    t: np.ndarray,
    group: np.ndarray | None,
    sigma_axes: tuple[float, float, float],
    n1: int,
    n2: int,
    max_gap: float,
) -> np.ndarray:
    """Score = max |eq. 17| over X, Y, Z, with the grouping and segment rules done by hand."""
    n = t.size
    group = np.zeros(n, dtype=int) if group is None else group
    score = np.full(n, np.nan)
    for g in np.unique(group):
        members = [i for i in np.argsort(t, kind="stable") if group[i] == g]
        segments, current = [], [members[0]]
        for prev, nxt in zip(members[:-1], members[1:], strict=True):
            if t[nxt] - t[prev] > max_gap:
                segments.append(current)
                current = []
            current.append(nxt)
        segments.append(current)
        for seg in segments:
            if len(seg) < 4:
                continue
            ts = t[seg]
            for pos in range(len(seg)):
                rows = slow_window(pos, 0, len(seg), n1, n2)
                values = []
                for axis in range(3):
                    sig = np.full(len(seg), sigma_axes[axis])
                    values.append(
                        abs(slow_standardised_difference(ts, xyz[seg, axis], sig, pos, rows))
                    )
                score[seg[pos]] = max(values)
    return score


# --------------------------------------------------------------------------------------------
# Synthetic data
# --------------------------------------------------------------------------------------------


def trajectory(t: np.ndarray) -> np.ndarray:
    """A smooth (non-polynomial) path, (n, 3) metres."""
    return np.c_[3.0 * np.sin(t / 7.0), 2.0 * np.cos(t / 5.0), 0.01 * t**1.5]


def noisy_line(n: int, seed: int, sigma=(0.01, 0.01, 0.01), step=1e-3):
    """Irregularly timed smooth path with Gaussian noise; returns xyz (n, 3), t (n,)."""
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.5 * step, 1.5 * step, n))
    xyz = trajectory(t * (1.0 / (step * 100))) + rng.normal(0.0, 1.0, (n, 3)) * np.asarray(sigma)
    return xyz, t


# --------------------------------------------------------------------------------------------
# Fast kernels against the slow reference
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(("n1", "n2"), [(5, 5), (2, 7), (1, 2), (10, 3)])
def test_kernel_matches_slow_reference_irregular_times_varying_sigma(n1, n2):
    rng = np.random.default_rng(10 + n1 + 7 * n2)
    n = 300  # long enough for runs of sliced windows as well as gathered ones
    t = np.cumsum(rng.uniform(0.2, 1.5, n))  # irregular steps
    z = np.sin(t / 3.0) * 5.0 + rng.normal(0.0, 0.05, n)
    sigma = rng.uniform(0.01, 0.2, n)  # varying per-point sigma
    pos = np.arange(n, dtype=np.int64)
    lo, hi = window_bounds(pos, np.zeros(n, np.int64), np.full(n, n, np.int64), n1, n2)
    dz, sdz = window_differences(t, z[:, None], sigma, pos, lo, hi)
    fast = dz[:, 0] / sdz
    slow = np.array(
        [slow_standardised_difference(t, z, sigma, k, slow_window(k, 0, n, n1, n2)) for k in pos]
    )
    np.testing.assert_allclose(fast, slow, rtol=1e-9, atol=0)


def test_kernel_matches_slow_reference_short_segment_whole_window():
    rng = np.random.default_rng(5)
    n = 7  # shorter than n1 + n2 + 1 = 11: the window is the whole segment
    t = np.cumsum(rng.uniform(0.5, 1.5, n))
    z = rng.normal(0.0, 1.0, n)
    sigma = rng.uniform(0.5, 2.0, n)
    pos = np.arange(n, dtype=np.int64)
    lo, hi = window_bounds(pos, np.zeros(n, np.int64), np.full(n, n, np.int64), 5, 5)
    assert np.all(lo == 0) and np.all(hi == n)
    dz, sdz = window_differences(t, z[:, None], sigma, pos, lo, hi)
    slow = [slow_standardised_difference(t, z, sigma, k, range(n)) for k in pos]
    np.testing.assert_allclose(dz[:, 0] / sdz, slow, rtol=1e-9)


def test_detector_matches_slow_reference_with_groups_and_gaps():
    rng = np.random.default_rng(42)
    n = 400
    t = np.cumsum(rng.uniform(0.3, 1.2, n))
    t[150:] += 20.0  # a gap
    t[300:] += 20.0  # another one
    xyz = trajectory(t) + rng.normal(0.0, 0.01, (n, 3))
    xyz[[30, 200, 333]] += [0.2, -0.1, 0.3]
    group = rng.integers(0, 2, n)
    order = rng.permutation(n)  # any input order
    xyz, t, group = xyz[order], t[order], group[order]
    sigma = (0.01, 0.02, 0.015)
    res = detect_temporal(xyz, t, group, n1=4, n2=6, sigma=sigma, max_gap=5.0)
    slow = slow_detect(xyz, t, group, sigma, 4, 6, 5.0)
    np.testing.assert_array_equal(np.isnan(res.score), np.isnan(slow))
    np.testing.assert_allclose(res.score, slow, rtol=1e-9)
    assert np.array_equal(res.flagged, slow > normal_critical_value(0.001))


def segmented_series(seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """t (n,), xyz (n, 3) and group bounds of two groups cut by gaps into segments of 1 to 400
    points (shorter than 4, shorter than a window, and long)."""
    rng = np.random.default_rng(seed)
    lengths = rng.choice([1, 3, 5, 9, 40, 400], 30)
    steps = np.concatenate([np.r_[50.0, rng.uniform(0.2, 1.5, m - 1)] for m in lengths])
    t = np.cumsum(steps)
    xyz = trajectory(t / 50.0) + rng.normal(0.0, 0.01, (t.size, 3))
    return t, xyz, np.array([0, t.size // 2, t.size])


def test_sliced_and_gathered_windows_give_identical_bits():
    t, xyz, bounds = segmented_series(3)
    n = t.size
    lo, hi, _, _ = segment_windows(t, bounds, np.array([10.0, 10.0]), 5, 5)
    starts, ends = cut_segments(t, bounds, np.array([10.0, 10.0]))
    sliced = segment_differences(t, np.ascontiguousarray(xyz.T), starts, ends, 5, 5,
                                 compiled=False)
    perm = np.random.default_rng(0).permutation(n)  # no consecutive targets: all gathered
    dz, sdz = window_differences(t, xyz, np.empty(0), perm, lo[perm], hi[perm], compiled=False)
    gathered = np.empty_like(dz), np.empty_like(sdz)
    gathered[0][perm], gathered[1][perm] = dz, sdz
    assert np.isfinite(sliced[1]).sum() > n // 2
    np.testing.assert_array_equal(sliced[0], gathered[0])
    np.testing.assert_array_equal(sliced[1], gathered[1])


def test_results_do_not_depend_on_blocks_or_threads(monkeypatch):
    t, xyz, bounds = segmented_series(4)
    starts, ends = cut_segments(t, bounds, np.array([10.0, 10.0]))
    z = np.ascontiguousarray(xyz.T)
    reference = segment_differences(t, z, starts, ends, 4, 6, compiled=False)
    monkeypatch.setattr(windows, "_BLOCK", 37)
    monkeypatch.setattr(windows, "_PARALLEL_POINTS", 0)
    for threads in ("1", "2", "3"):
        monkeypatch.setenv("NUMBA_NUM_THREADS", threads)
        dz, sdz = segment_differences(t, z, starts, ends, 4, 6, compiled=False)
        np.testing.assert_array_equal(dz, reference[0])
        np.testing.assert_array_equal(sdz, reference[1])


def series_with_repeated_times(seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``segmented_series`` with runs of 20 equal times: windows inside them hold fewer than
    three distinct times and are untested."""
    t, xyz, bounds = segmented_series(seed)
    t = t.copy()
    for a in np.random.default_rng(seed).choice(t.size - 21, 6, replace=False):
        t[a : a + 20] = t[a]
    return t, xyz, bounds


@pytest.mark.parametrize("seed", [5, 6, 7])
@pytest.mark.parametrize(("n1", "n2"), [(5, 5), (1, 2), (10, 3), (0, 6)])
def test_compiled_smoother_gives_the_numpy_bits(seed, n1, n2):
    """The compiled smoother runs the numpy blocks' operations in their order: equal bits,
    for every row of cut segments (sliced, shared and gathered windows) and for any windows."""
    t, xyz, bounds = series_with_repeated_times(seed)
    gaps = np.array([10.0, 10.0])
    starts, ends = cut_segments(t, bounds, gaps)
    z = np.ascontiguousarray(xyz.T)
    numpy_rows = segment_differences(t, z, starts, ends, n1, n2, compiled=False)
    compiled_rows = segment_differences(t, z, starts, ends, n1, n2, compiled=True)
    assert np.isnan(numpy_rows[1]).sum() > 20 and np.isfinite(numpy_rows[1]).sum() > 1000
    for a, b in zip(numpy_rows, compiled_rows, strict=True):
        np.testing.assert_array_equal(a, b)
    lo, hi, _, _ = segment_windows(t, bounds, gaps, n1, n2)
    perm = np.random.default_rng(seed).permutation(t.size)
    for runs in (np.arange(t.size), perm):  # consecutive windows, then scattered ones
        expected = window_differences(t, xyz, np.empty(0), runs, lo[runs], hi[runs],
                                      compiled=False)
        got = window_differences(t, xyz, np.empty(0), runs, lo[runs], hi[runs], compiled=True)
        for a, b in zip(expected, got, strict=True):
            np.testing.assert_array_equal(a, b)


def test_compiled_smoother_is_chosen_for_long_series_or_when_numba_is_loaded(monkeypatch):
    import sys

    monkeypatch.delitem(sys.modules, "numba", raising=False)
    assert not windows.use_compiled(windows.COMPILED_MIN_WINDOWS - 1)
    assert windows.use_compiled(windows.COMPILED_MIN_WINDOWS)
    monkeypatch.setitem(sys.modules, "numba", object())
    assert windows.use_compiled(1)


# --------------------------------------------------------------------------------------------
# Properties
# --------------------------------------------------------------------------------------------


def test_exact_quadratic_trajectory_scores_zero():
    rng = np.random.default_rng(1)
    t = np.cumsum(rng.uniform(0.5e-5, 1.5e-5, 300))
    tc = t - t[0]
    xyz = np.c_[1.0 + 20.0 * tc - 3e3 * tc**2, 2.0 - 5.0 * tc, 0.5 + 1e4 * tc**2]
    res = detect_temporal(xyz, t, sigma=0.01)
    assert np.all(np.isfinite(res.score))
    assert np.max(res.score) < 1e-6
    assert not res.flagged.any()


def test_ten_sigma_spike_is_flagged_and_its_neighbours_are_not():
    sigma = 0.01
    rng = np.random.default_rng(7)
    t = np.cumsum(rng.uniform(0.5, 1.5, 200))
    xyz = np.c_[0.1 * t, 2.0 - 0.003 * t**2, np.full_like(t, 5.0)]  # exact quadratic
    spike = 100
    xyz[spike, 2] += 10 * sigma
    res = detect_temporal(xyz, t, sigma=sigma)
    assert res.flagged[spike] and res.score[spike] > 8.0
    # The spike enters its neighbours' predictions (eq. 15) with weight a_i / (1 - a_0), which
    # lifts their scores to at most ~2.5 here: below the critical value 3.29.
    neighbours = np.r_[spike - 5 : spike, spike + 1 : spike + 6]
    assert np.all(res.score[neighbours] < normal_critical_value(0.001))
    assert np.flatnonzero(res.flagged).tolist() == [spike]


def test_ten_sigma_spikes_in_noise_are_flagged():
    sigma = 0.01
    xyz, t = noisy_line(4000, seed=7, sigma=(sigma,) * 3)
    spikes = np.arange(100, 3900, 50)
    rng = np.random.default_rng(70)
    axis = rng.integers(0, 3, spikes.size)
    xyz[spikes, axis] += 10 * sigma * rng.choice([-1.0, 1.0], spikes.size)
    res = detect_temporal(xyz, t, sigma=sigma)
    assert res.flagged[spikes].all()
    near = np.concatenate([np.r_[s - 5 : s, s + 1 : s + 6] for s in spikes])
    far = np.setdiff1d(np.arange(t.size), np.concatenate([np.r_[s - 5 : s + 6] for s in spikes]))
    # Neighbours carry ~2.5 sigma of the spike plus their own noise: some are swamped (~5 %),
    # points far from spikes are flagged at the test's false-alarm rate (~3 x alpha for 3 axes).
    assert res.flagged[near].mean() < 0.10
    assert res.flagged[far].mean() < 0.01


def test_shift_by_exactly_representable_offsets_changes_nothing():
    # Times on a 2^-17 s grid and coordinates on a 2^-10 m grid stay exact after shifting by
    # 1e5 s and 5e6 m, so only an implementation that forms sums of raw t^4 or z could differ.
    rng = np.random.default_rng(3)
    t = 4e5 + np.cumsum(rng.integers(1, 3, 3000)) * 2.0**-17
    xyz = np.round(trajectory((t - 4e5) * 1e3) * 1024) / 1024
    xyz[500] += 0.0625  # on the grid too
    base = detect_temporal(xyz, t, sigma=0.002)
    shifted = detect_temporal(xyz + 5e6, t + 1e5, sigma=0.002)
    assert np.array_equal(base.score, shifted.score, equal_nan=True)
    assert base.flagged[500] and shifted.flagged[500]


def test_shift_of_time_and_coordinates_keeps_scores_realistic_values():
    xyz, t = noisy_line(3000, seed=4, step=1e-5)
    xyz[1234, 0] += 0.1
    base = detect_temporal(xyz, t, sigma=0.01)
    shifted = detect_temporal(xyz + np.array([5e6, 5e6, 5e6]), t + 5e5, sigma=0.01)
    # Only the rounding of the shifted inputs differs (ulp(5e5 s) = 6e-11 s vs steps of 1e-5 s).
    np.testing.assert_allclose(shifted.score, base.score, rtol=1e-4, atol=1e-4)
    assert np.array_equal(base.flagged, shifted.flagged)
    assert shifted.flagged[1234]


def test_segments_split_at_gaps():
    xyz, t = noisy_line(600, seed=5)
    t = t.copy()
    t[300:] += 1.0  # a gap of ~1000 median steps
    res = detect_temporal(xyz, t, sigma=0.01)
    assert res.info["segments"] == 2
    # Each segment alone gives the same scores: no window crosses the gap.
    gap = res.info["max_gap_by_group"]["0"]
    first = detect_temporal(xyz[:300], t[:300], sigma=0.01, max_gap=gap)
    second = detect_temporal(xyz[300:], t[300:], sigma=0.01, max_gap=gap)
    np.testing.assert_array_equal(res.score, np.r_[first.score, second.score])
    # Without the split (a huge max_gap) the points next to the gap change.
    joined = detect_temporal(xyz, t, sigma=0.01, max_gap=10.0)
    assert joined.info["segments"] == 1
    assert not np.allclose(joined.score[295:305], res.score[295:305])


def test_max_gap_auto_is_five_median_steps():
    t = np.arange(100) * 0.5
    t[50:] += 2.0  # step of 2.5 = exactly 5 x median: not a gap (strictly greater splits)
    xyz = trajectory(t)
    res = detect_temporal(xyz, t, sigma=0.01)
    assert res.info["max_gap_by_group"] == {"0": 2.5}
    assert res.info["segments"] == 1
    t[50:] += 1e-6
    assert detect_temporal(xyz, t, sigma=0.01).info["segments"] == 2


def test_window_shifts_at_segment_ends():
    t = np.arange(30, dtype=np.float64)
    group_bounds = np.array([0, 30], dtype=np.int64)
    lo, hi, n_seg, n_short = segment_windows(t, group_bounds, np.array([10.0]), 5, 5)
    assert (n_seg, n_short) == (1, 0)
    assert (lo[0], hi[0]) == (0, 11)  # start: window shifted right, still 10 neighbours
    assert (lo[3], hi[3]) == (0, 11)
    assert (lo[15], hi[15]) == (10, 21)  # middle: [k - 5, k + 5]
    assert (lo[29], hi[29]) == (19, 30)  # end: shifted left
    assert np.all(hi - lo == 11)
    # The detector uses the shifted window: the first point's score equals the slow reference
    # with rows 0..10, not with the truncated window 0..5.
    rng = np.random.default_rng(8)
    z = np.sin(t / 4.0) + rng.normal(0.0, 0.01, 30)
    xyz = np.c_[z, np.zeros(30), np.zeros(30)]
    res = detect_temporal(xyz, t, sigma=0.01, max_gap=10.0)
    sig = np.full(30, 0.01)
    shifted = abs(slow_standardised_difference(t, z, sig, 0, range(0, 11)))
    truncated = abs(slow_standardised_difference(t, z, sig, 0, range(0, 6)))
    assert res.score[0] == pytest.approx(shifted, rel=1e-9)
    assert res.score[0] != pytest.approx(truncated, rel=1e-3)


def test_segments_shorter_than_four_points_are_untested():
    t = np.r_[0.0, 1.0, 2.0, 100.0, 101.0, 102.0, 103.0, 200.0, 300.0, 301.0]
    xyz = np.c_[t * 0.1, t**2 * 0.01, np.ones_like(t)]
    res = detect_temporal(xyz, t, sigma=0.01, max_gap=10.0)
    expected_tested = np.r_[[False] * 3, [True] * 4, [False] * 3]
    np.testing.assert_array_equal(res.tested, expected_tested)
    assert not res.flagged[~expected_tested].any()
    assert res.info["segments"] == 4 and res.info["segments_untested"] == 3
    assert res.info["points_tested"] == 4


def test_grouping_by_scanner_separates_the_series():
    rng = np.random.default_rng(9)
    n = 1000
    t = np.sort(rng.uniform(0.0, 1.0, n))
    group = rng.integers(1, 3, n).astype(np.uint16)  # two interleaved scanners
    xyz = np.where((group == 1)[:, None], trajectory(t * 50), trajectory(t * 50) + [3.0, -2.0, 1.0])
    xyz = xyz + rng.normal(0.0, 0.01, (n, 3))
    res = detect_temporal(xyz, t, group, sigma=0.01)
    assert res.info["groups"] == 2 and set(res.info["max_gap_by_group"]) == {"1", "2"}
    for g in (1, 2):
        m = group == g
        alone = detect_temporal(xyz[m], t[m], sigma=0.01)
        np.testing.assert_array_equal(res.score[m], alone.score)
    assert res.flagged.sum() <= 3
    # Mixed into one series the 3 m offset between the scanners is "outlying" everywhere.
    mixed = detect_temporal(xyz, t, None, sigma=0.01)
    assert mixed.flagged.mean() > 0.5


def test_auto_sigma_recovers_true_sigma_per_axis():
    sigma = (0.01, 0.02, 0.005)
    xyz, t = noisy_line(20000, seed=11, sigma=sigma)
    rng = np.random.default_rng(12)
    bad = rng.choice(t.size, 100, replace=False)  # 0.5 % gross outliers
    xyz[bad] += rng.normal(0.0, 1.0, (100, 3))
    res = detect_temporal(xyz, t)
    est = res.info["sigma"]
    assert res.info["sigma_source"] == "mad"
    for axis, true in zip("xyz", sigma, strict=True):
        assert est[axis] == pytest.approx(true, rel=0.10)
    assert res.flagged[bad].mean() > 0.9


def test_input_order_does_not_matter():
    xyz, t = noisy_line(500, seed=13)
    group = np.random.default_rng(14).integers(0, 3, 500)
    perm = np.random.default_rng(15).permutation(500)
    a = detect_temporal(xyz, t, group, sigma=0.01)
    b = detect_temporal(xyz[perm], t[perm], group[perm], sigma=0.01)
    np.testing.assert_array_equal(a.score[perm], b.score)


def test_nan_time_and_nonfinite_points_are_untested_and_skipped():
    xyz, t = noisy_line(200, seed=16)
    t_nan, xyz_nan = t.copy(), xyz.copy()
    t_nan[50] = np.nan
    xyz_nan[120, 1] = np.inf
    res = detect_temporal(xyz_nan, t_nan, sigma=0.01)
    keep = np.setdiff1d(np.arange(200), [50, 120])
    alone = detect_temporal(xyz[keep], t[keep], sigma=0.01)
    assert np.isnan(res.score[50]) and np.isnan(res.score[120])
    assert not res.flagged[50] and not res.flagged[120]
    np.testing.assert_array_equal(res.score[keep], alone.score)


def test_info_is_json_and_complete():
    xyz, t = noisy_line(300, seed=17)
    res = detect_temporal(xyz, t, np.zeros(300, np.int32))
    info = json.loads(json.dumps(res.info, allow_nan=False))
    for key in ("n1", "n2", "alpha", "critical_value", "sigma", "max_gap", "max_gap_by_group",
                "points", "points_tested", "points_flagged", "segments", "segments_untested"):
        assert key in info
    assert info["critical_value"] == pytest.approx(normal_critical_value(0.001))
    assert info["points"] == 300 and info["points_tested"] == 300
    assert res.critical_value == info["critical_value"]


def test_empty_input():
    res = detect_temporal(np.zeros((0, 3)), np.zeros(0), sigma=0.01)
    assert res.score.shape == (0,) and res.flagged.shape == (0,)
    assert res.info["points"] == 0


# --------------------------------------------------------------------------------------------
# Bad input
# --------------------------------------------------------------------------------------------


def test_missing_gps_time_is_a_missing_dimension():
    with pytest.raises(MissingDimensionError, match="gps_time"):
        detect_temporal(np.zeros((5, 3)), None)
    with pytest.raises(MissingDimensionError, match="gps_time"):
        detect_temporal(np.zeros((5, 3)), np.full(5, np.nan))


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"n1": 0}, "n1"),
        ({"n2": 1.5}, "n2"),
        ({"n1": 1, "n2": 1}, "n1 \\+ n2"),
        ({"sigma": -1.0}, "sigma"),
        ({"sigma": "robust"}, "sigma"),
        ({"sigma": (0.01, 0.02)}, "sigma"),
        ({"alpha": 0.0}, "alpha"),
        ({"alpha": 0.7}, "alpha"),
        ({"max_gap": 0.0}, "max_gap"),
        ({"max_gap": "never"}, "max_gap"),
    ],
)
def test_bad_parameters_are_refused_with_their_name(kwargs, message):
    xyz, t = noisy_line(50, seed=18)
    with pytest.raises(ParameterError, match=message):
        detect_temporal(xyz, t, **kwargs)


def test_bad_shapes_are_refused():
    xyz, t = noisy_line(50, seed=19)
    with pytest.raises(ParameterError, match="xyz"):
        detect_temporal(xyz[:, :2], t)
    with pytest.raises(ParameterError, match="gps_time"):
        detect_temporal(xyz, t[:-1])
    with pytest.raises(ParameterError, match="group"):
        detect_temporal(xyz, t, np.zeros(49, int))
    with pytest.raises(ParameterError, match="group"):
        detect_temporal(xyz, t, np.zeros(50))


# --------------------------------------------------------------------------------------------
# Streaming
# --------------------------------------------------------------------------------------------


def _stream_data(n: int = 4000, seed: int = 20):
    """Two interleaved scanners, time-ordered as in a file, gaps, outliers, NaN times."""
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.5, 1.5, n))
    for cut in rng.choice(n, 25, replace=False):
        t[cut:] += rng.choice([30.0, 2.0])  # some gaps, some not
    group = rng.integers(0, 2, n).astype(np.uint16)
    xyz = trajectory(t / 30.0) + rng.normal(0.0, 0.01, (n, 3))
    xyz[rng.choice(n, 20, replace=False)] += 0.2
    t[rng.choice(n, 5, replace=False)] = np.nan
    return xyz, t, group


def _run_stream(stream: TemporalStream, xyz, t, group, chunk: int) -> np.ndarray:
    n = t.size
    score = np.full(n, -1.0)
    seen = np.zeros(n, dtype=int)
    for a in range(0, n, chunk):
        sl = slice(a, min(n, a + chunk))
        idx, s = stream.push(xyz[sl], t[sl], group[sl], np.arange(n)[sl])
        score[idx] = s
        seen[idx] += 1
    idx, s = stream.finish()
    score[idx] = s
    seen[idx] += 1
    assert np.all(seen == 1)  # every point reported exactly once
    return score


@pytest.mark.parametrize("chunk", [1, 3, 11, 64, 500, 4000])
def test_stream_equals_batch_exactly(chunk):
    xyz, t, group = _stream_data()
    batch = detect_temporal(xyz, t, group, sigma=0.01, max_gap=6.0)
    stream = TemporalStream(sigma=0.01, max_gap=6.0)
    score = _run_stream(stream, xyz, t, group, chunk)
    np.testing.assert_array_equal(score, batch.score)
    assert stream.info["segments"] == batch.info["segments"]
    assert stream.info["points_flagged"] == batch.info["points_flagged"]
    assert stream.critical_value == batch.critical_value


def test_stream_gives_the_same_bits_with_either_smoother_and_when_it_switches():
    xyz, t, group = _stream_data(6000, seed=24)
    scores = []
    for compiled in (False, True, "switch"):
        stream = TemporalStream(sigma=0.01, max_gap=6.0, compiled=compiled is True)
        score = np.full(t.size, -1.0)
        for a in range(0, t.size, 500):
            if compiled == "switch":
                stream.compiled = a >= 3000
            idx, s = stream.push(xyz[a:a + 500], t[a:a + 500], group[a:a + 500],
                                 np.arange(a, min(a + 500, t.size)))
            score[idx] = s
        idx, s = stream.finish()
        score[idx] = s
        scores.append(score)
    assert np.isfinite(scores[0]).sum() > 5000
    np.testing.assert_array_equal(scores[0], scores[1])
    np.testing.assert_array_equal(scores[0], scores[2])


def test_stream_holds_back_a_bounded_tail():
    xyz, t, group = _stream_data(20000, seed=21)
    stream = TemporalStream(sigma=0.01, max_gap=6.0, n1=5, n2=5)
    for a in range(0, t.size, 1000):
        stream.push(xyz[a : a + 1000], t[a : a + 1000], group[a : a + 1000], np.arange(a, a + 1000))
        held = sum(tail.t.size for tail in stream._tails.values())
        assert held <= 2 * 2 * (5 + 5 + 1)  # two groups, context + pending each


def test_stream_auto_resolves_from_warmup():
    xyz, t, group = _stream_data(6000, seed=22)
    stream = TemporalStream(warmup_points=2000)
    score = _run_stream(stream, xyz, t, group, 500)
    info = stream.info
    assert info["sigma_source"] == "mad"
    for axis in "xyz":
        assert info["sigma"][axis] == pytest.approx(0.01, rel=0.15)
    # With the values the warmup resolved made explicit, the batch detector agrees exactly.
    gaps = info["max_gap_by_group"]
    assert set(gaps) == {"0", "1"}
    sigma = tuple(info["sigma"][axis] for axis in "xyz")
    for g in (0, 1):
        m = group == g
        batch = detect_temporal(xyz[m], t[m], sigma=sigma, max_gap=gaps[str(g)])
        np.testing.assert_array_equal(score[m], batch.score)


def test_stream_differences_with_the_batch_gaps_give_the_batch_auto_result():
    """Given each group's max_gap as the batch resolves it, the unit differences a stream
    returns give the batch's sigma (from the same sample) and its scores, bit for bit."""
    from algorithms.temporal.batch import estimate_sigma, scores_from_differences

    xyz, t, group = _stream_data(6000, seed=23)
    batch = detect_temporal(xyz, t, group)
    gaps = {int(g): v for g, v in batch.info["max_gap_by_group"].items()}
    stream = TemporalStream(sigma=1.0, max_gap_by_group=gaps, differences=True)
    diffs = np.full((t.size, 4), -1.0)
    for a in range(0, t.size, 700):
        idx, d = stream.push(xyz[a:a + 700], t[a:a + 700], group[a:a + 700],
                             np.arange(a, min(a + 700, t.size)))
        diffs[idx] = d
    idx, d = stream.finish()
    diffs[idx] = d
    assert not np.any(diffs == -1.0)
    valid = np.isfinite(t)
    order = np.lexsort((t[valid], group[valid]))  # the batch's (scanner, time) order
    rows = diffs[valid][order]
    sigma, source = estimate_sigma(rows[:, :3], rows[:, 3])
    assert source == batch.info["sigma_source"]
    assert [batch.info["sigma"][a] for a in "xyz"] == sigma.tolist()
    score = scores_from_differences(diffs[:, :3], diffs[:, 3], sigma)
    np.testing.assert_array_equal(score, batch.score)
    assert stream.info["segments"] == batch.info["segments"]


def test_stream_refuses_unsorted_time_within_group():
    stream = TemporalStream(sigma=0.01, max_gap=1.0)
    xyz = np.zeros((3, 3))
    stream.push(xyz, np.array([0.0, 1.0, 2.0]), None, np.arange(3))
    with pytest.raises(NotTimeOrderedError, match="ordered by gps_time"):
        stream.push(xyz, np.array([1.5, 3.0, 4.0]), None, np.arange(3, 6))
    assert issubclass(NotTimeOrderedError, ParameterError)


# --------------------------------------------------------------------------------------------
# Real LAS files
# --------------------------------------------------------------------------------------------

DATA = Path(__file__).resolve().parents[1] / "data"


def test_las_round_trip_near_5e6_m_and_5e5_s(tmp_path):
    """Coordinates stored as integers with a 5e6 m offset and times near 5e5 s, read by laspy."""
    xyz, t = noisy_line(5000, seed=30, step=1e-5)
    xyz[2500, 1] += 0.08
    path = write_las(tmp_path / "line.las", xyz + [5e6, 5e6, 0.0], gps_time=t + 5e5,
                     point_format=6, offsets=(5e6, 5e6, 0.0),
                     point_source_id=np.ones(t.size, dtype=np.uint16), vlrs=())

    back = laspy.read(path)
    xyz_file = np.c_[back.x, back.y, back.z]
    res = detect_temporal(xyz_file, np.asarray(back.gps_time), np.asarray(back.point_source_id))
    # The same points centred by hand (integer coordinates x scale) and times near 0.
    local = np.c_[back.X, back.Y, back.Z] * 0.001
    ref = detect_temporal(local, np.asarray(back.gps_time) - 5e5)
    np.testing.assert_allclose(res.score, ref.score, rtol=1e-5, atol=1e-5)
    assert res.flagged[2500]
    assert res.info["sigma"]["x"] == pytest.approx(0.01, rel=0.1)


def test_real_airborne_gross_outliers_are_found():
    """laspy's append-bug.laz: 4 flight lines, gps_time, producer-labelled artefacts (class 65).

    Airborne scan lines with multiple returns per pulse are not the smooth series the paper
    assumes, so false alarms are high here (about 37 % with sigma 'auto', measured); the test
    pins the recall of the gross outliers, and the false alarms with a loose sigma of 1 m.
    """
    las = laspy.read(DATA / "airborne" / "laspy__append-bug.laz")
    truth = np.load(DATA / "airborne" / "laspy__append-bug.truth.npz")
    xyz = np.c_[las.x, las.y, las.z]
    res = detect_temporal(xyz, np.asarray(las.gps_time), np.asarray(las.point_source_id))
    assert res.info["groups"] == 4
    assert res.flagged[truth["gross"]].mean() > 0.9  # 0.928 measured
    loose = detect_temporal(
        xyz, np.asarray(las.gps_time), np.asarray(las.point_source_id), sigma=1.0
    )
    assert loose.flagged[truth["gross"]].mean() > 0.9  # 0.910 measured
    assert loose.flagged[~truth["is_outlier"]].mean() < 0.06  # 0.053 measured


def test_stream_group_first_seen_after_warmup_resolves_its_own_max_gap():
    xyz, t, _ = _stream_data(3000, seed=23)
    group = np.where(np.arange(3000) < 1500, 0, 1 + np.arange(3000) % 2)  # 1, 2 appear late
    stream = TemporalStream(sigma=0.01, warmup_points=1000)
    score = _run_stream(stream, xyz, t, group, 500)
    gaps = stream.info["max_gap_by_group"]
    assert set(gaps) == {"0", "1", "2"}
    for g in (1, 2):
        rows = np.flatnonzero(group == g)
        first_chunk = rows[rows < 2000]  # the group's rows in the first chunk that holds it
        times = t[first_chunk][np.isfinite(t[first_chunk])]
        steps = np.diff(times)
        assert gaps[str(g)] == pytest.approx(5 * np.median(steps[steps > 0]), rel=1e-12)
        batch = detect_temporal(xyz[rows], t[rows], sigma=0.01, max_gap=gaps[str(g)])
        np.testing.assert_array_equal(score[rows], batch.score)
