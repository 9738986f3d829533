"""Where a scanner stood still, from its own points and times.

A profile scanner fires the same beams on every turn of its mirror. While the vehicle stands
still, those beams meet the same spots again and again: a window of a tenth of a second holds
5-25 turns whose returns, with the mirror's phase drifting from turn to turn, lie millimetres
apart on every surface, and the returns of a window a few tenths of a second later lie on top
of them. Moving at v, that later window's profile lies v x the lag away (1 cm at 5 cm/s over
0.2 s). So the time series of one scanner is cut into windows of ``window`` seconds, a spread
sample of each window's points is compared with all points of the window ``lag`` windows later,
and where the median distance to the later profile (the line through the two nearest of its
returns: pulses a degree apart leave centimetres between them along the scan line, none across
it) is at most ``tolerance`` the scanner stood still from the start of the first window to the
end of the second. Airborne returns and moving objects in a window do not move the median.
numpy in, numpy out (scipy's k-d tree).
"""

from __future__ import annotations

import numpy as np

from algorithms.checks import check_xyz
from algorithms.errors import ParameterError

#: Seconds of one window.
WINDOW = 0.1
#: Windows between the two compared (0.3 s at WINDOW: a vehicle creeping at 2 cm/s has moved
#: more than the tolerance).
LAG = 3
#: Metres: the median distance of a still scanner's returns to the later window's profile (range
#: noise of a few millimetres).
TOLERANCE = 0.005
#: Points of a window compared (a spread sample in time order).
SAMPLE = 256
#: Fewer points than this in either window: nothing is decided there.
MIN_WINDOW_POINTS = 20


def profile_distances(points: np.ndarray, later: np.ndarray) -> np.ndarray:
    """(n,) distance from each of ``points`` (n, 3) to the line through its two nearest
    returns among ``later`` (m >= 2, 3): on a still scanner's profile those bracket it along
    the scan line, however far apart the pulses are, and the line passes within the range noise;
    where they coincide, the distance to the nearest."""
    from scipy.spatial import cKDTree

    _, j = cKDTree(later).query(points, k=2)
    q1, q2 = later[j[:, 0]], later[j[:, 1]]
    along = q2 - q1
    length = np.linalg.norm(along, axis=1)
    to_p = points - q1
    across = np.linalg.norm(np.cross(to_p, along), axis=1) / np.where(length > 0, length, 1.0)
    return np.where(length > 0, across, np.linalg.norm(to_p, axis=1))


def window_still(earlier: np.ndarray, later: np.ndarray, tolerance: float, sample: int) -> bool:
    """Whether the median :func:`profile_distances` of a spread sample of the points
    ``earlier`` (n, 3), in time order, to ``later`` (m, 3) is at most ``tolerance`` metres."""
    pick = np.linspace(0, len(earlier) - 1, min(sample, len(earlier))).astype(np.int64)
    return bool(np.median(profile_distances(earlier[pick], later)) <= tolerance)


def still_spans(gps_time: np.ndarray, xyz: np.ndarray, *, window: float = WINDOW,
                lag: int = LAG, tolerance: float = TOLERANCE, sample: int = SAMPLE
                ) -> np.ndarray:
    """(m, 2) start and end times of the spans over which one scanner stood still (module
    docstring), in time order, overlapping spans merged.

    gps_time (n,) seconds of one scanner's returns (NaN: left out); xyz (n, 3) metres.
    """
    arr = check_xyz(xyz)
    t = np.asarray(gps_time, dtype=np.float64)
    if t.shape != (len(arr),):
        raise ParameterError(f"gps_time must have shape ({len(arr)},), got {t.shape}")
    if not (window > 0 and lag >= 1 and tolerance > 0 and sample >= 1):
        raise ParameterError("window and tolerance must be > 0, lag and sample >= 1")
    timed = np.flatnonzero(np.isfinite(t))
    if timed.size == 0:
        return np.zeros((0, 2))
    order = timed[np.argsort(t[timed], kind="stable")]
    ts, points = t[order], arr[order]
    which = np.floor((ts - ts[0]) / window).astype(np.int64)
    starts = np.searchsorted(which, np.arange(which[-1] + 2))
    spans = []
    for i in range(len(starts) - 1 - lag):
        a, b = slice(starts[i], starts[i + 1]), slice(starts[i + lag], starts[i + lag + 1])
        if min(a.stop - a.start, b.stop - b.start) < MIN_WINDOW_POINTS:
            continue
        if window_still(points[a], points[b], tolerance, sample):
            spans.append((ts[0] + i * window, ts[0] + (i + lag + 1) * window))
    return merged_spans(np.array(spans).reshape(-1, 2))


def merged_spans(spans: np.ndarray) -> np.ndarray:
    """(m, 2) spans sorted by start with those that overlap or touch joined."""
    if len(spans) == 0:
        return spans
    spans = spans[np.argsort(spans[:, 0], kind="stable")]
    out = [spans[0].copy()]
    for start, end in spans[1:]:
        if start <= out[-1][1]:
            out[-1][1] = max(out[-1][1], end)
        else:
            out.append(np.array([start, end]))
    return np.array(out)
