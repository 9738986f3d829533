"""Scan-line segments of the temporal detector: series cut at time gaps, and each row's window.

A scanner's points in GPS-time order form one series until a time step exceeds ``max_gap``
(a gap between scan lines or a lost stretch; "auto": 5 x the group's median positive time step,
``median_positive_step``); each piece is a segment, smoothed on its own. ``cut_segments``
cuts, ``segment_windows`` gives every row its window for the batch detector, and
``stream_windows`` the rows of a stream's buffer whose windows are final.
"""

from __future__ import annotations

import math

import numpy as np

from algorithms.temporal.smoother import MIN_SEGMENT_POINTS
from algorithms.temporal.windows import window_bounds


def _segment_of_rows(
    starts: np.ndarray, ends: np.ndarray, rows: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Start and end row of the segment holding each row (segments given sorted, contiguous)."""
    which = np.searchsorted(starts, rows, side="right") - 1
    return starts[which], ends[which]


def cut_segments(
    t: np.ndarray, group_bounds: np.ndarray, max_gap: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Cut sorted groups into segments at time gaps: (starts, ends) rows, covering 0:n in order.

    t : (n,) times sorted within each group; group g is rows group_bounds[g]:group_bounds[g+1].
    max_gap : (g,) seconds per group; a step t[r] - t[r-1] > max_gap starts a new segment.
    """
    n = t.shape[0]
    if n == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    group_sizes = np.diff(group_bounds)
    new_segment = np.zeros(n, dtype=bool)
    new_segment[group_bounds[:-1][group_sizes > 0]] = True
    new_segment[1:] |= np.diff(t) > np.repeat(np.asarray(max_gap, np.float64), group_sizes)[1:]
    starts = np.flatnonzero(new_segment)
    return starts, np.r_[starts[1:], n]


def segment_windows(
    t: np.ndarray, group_bounds: np.ndarray, max_gap: np.ndarray, n1: int, n2: int
) -> tuple[np.ndarray, np.ndarray, int, int]:
    """``cut_segments``, then every row's window: lo, hi (n,) int64 as ``window_bounds``, the
    number of segments and the number shorter than MIN_SEGMENT_POINTS (left untested)."""
    starts, ends = cut_segments(t, group_bounds, max_gap)
    lengths = ends - starts
    lo, hi = window_bounds(
        np.arange(t.shape[0]), np.repeat(starts, lengths), np.repeat(ends, lengths), n1, n2
    )
    return lo, hi, int(starts.size), int(np.count_nonzero(lengths < MIN_SEGMENT_POINTS))


def stream_windows(
    t: np.ndarray, max_gap: float, seg_start: int, done: int, n1: int, n2: int, final: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, int, int, int]:
    """The rows of one group's stream buffer that can be scored now, with their windows.

    t : (n,) sorted times of the buffer. seg_start : row where the buffer's first segment began
    (<= 0: it may have begun in an earlier chunk). done : rows before it are scored already.
    A segment ended by a time gap (or by ``final``) gets the batch rule of ``segment_windows``.
    In the open last segment a row is final once n2 rows follow it and the segment holds
    n1 + n2 + 1 rows: its window [max(k - n1, start), + n1 + n2 + 1) cannot shift any more.

    Returns targets, lo, hi (p,) int64, the new ``done``, the open segment's start row, and the
    numbers of segments closed and of those shorter than MIN_SEGMENT_POINTS.
    """
    n = t.shape[0]
    size = n1 + n2 + 1
    cuts = np.flatnonzero(np.diff(t) > max_gap) + 1
    starts = np.r_[seg_start, cuts].astype(np.int64)
    ends = np.r_[cuts, n].astype(np.int64)
    closed = starts.size if final and n > 0 else starts.size - 1
    open_start = n if closed == starts.size else int(starts[-1])
    n_short = int(np.count_nonzero(ends[:closed] - starts[:closed] < MIN_SEGMENT_POINTS))

    # Rows of closed segments: the batch rule.
    rows = np.arange(done, open_start, dtype=np.int64)
    lo, hi = window_bounds(rows, *_segment_of_rows(starts, ends, rows), n1, n2)
    new_done = max(done, open_start)
    # Rows of the open segment whose window can no longer shift.
    if open_start < n and n - open_start >= size and new_done < n - n2:
        rows_open = np.arange(new_done, n - n2, dtype=np.int64)
        lo_open = np.maximum(rows_open - n1, open_start)
        rows = np.r_[rows, rows_open]
        lo = np.r_[lo, lo_open]
        hi = np.r_[hi, lo_open + size]
        new_done = n - n2
    return rows, lo, hi, new_done, open_start, int(closed), n_short


def median_positive_step(t: np.ndarray) -> float:
    """Median of the positive steps of a sorted time series; NaN if it has none."""
    dt = np.diff(t)
    dt = dt[dt > 0]
    if dt.size == 0:
        return math.nan
    middle = (dt.size - 1) // 2  # np.median's two middle values, without its NaN pass
    dt.partition([middle, dt.size // 2])
    return float((dt[middle] + dt[dt.size // 2]) / 2.0)
