"""The batch temporal detector, ``detect_temporal``: a whole cloud at once (eqs. 1-17).

Valid points are sorted by (scanner, time) and cut into segments
(:mod:`algorithms.temporal.segments`); eqs. 15 and 16 are evaluated once with unit sigma
(:mod:`algorithms.temporal.windows`); sigma is given or estimated robustly per axis from those
unit-sigma differences (``estimate_sigma``), and a point's score is the largest |eq. 17| over
X, Y, Z (``scores_from_differences``): eq. 16 scales with sigma and the a_i of eq. 11 do not
depend on a common sigma, so one pass serves any sigma.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from algorithms.errors import MissingDimensionError
from algorithms.result import DetectorResult
from algorithms.stats import mad_sigma
from algorithms.temporal.parameters import ResolvedParameters, check_arrays, check_params
from algorithms.temporal.segments import cut_segments, median_positive_step
from algorithms.temporal.smoother import MIN_SEGMENT_POINTS, standardised_difference
from algorithms.temporal.windows import segment_differences

#: Tested points above which ``estimate_sigma`` works on an evenly strided subsample.
SIGMA_SAMPLE_POINTS = 100_000


def _sort_order(t: np.ndarray, group: np.ndarray | None) -> np.ndarray | None:
    """Stable order by (group, time); None when the input is in that order already.

    Files are usually time-ordered, so the common cases avoid a full lexsort: no sort at all, or
    a stable (radix, for 16-bit ids) sort by group that keeps the time order within each group.
    """
    if t.size == 0:
        return None
    if np.all(t[1:] >= t[:-1]):
        if group is None or np.all(group[1:] >= group[:-1]):
            return None
        return np.argsort(group, kind="stable")
    if group is None:
        return np.argsort(t, kind="stable")
    return np.lexsort((t, group))


def finite_points(xyz: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(n,) bool: the points the detector uses, with a finite time and position. Column by
    column: ``np.isfinite(xyz).all(axis=1)`` over three columns is about 15x slower."""
    valid = np.isfinite(t)
    for axis in range(3):
        valid &= np.isfinite(xyz[:, axis])
    return valid


@dataclass
class SortedPoints:
    """Valid points in (group, time) order, cut into segments."""

    rows: np.ndarray | None  # (m,) original row of each sorted point; None: identity, m = n
    t: np.ndarray  # (m,)
    z: np.ndarray  # (3, m) X, Y, Z rows, C-contiguous
    starts: np.ndarray  # (segments,) first row of each segment
    ends: np.ndarray  # (segments,) row after its last
    max_gap_by_group: dict[int, float | None]

    @property
    def n_segments(self) -> int:
        return int(self.starts.size)

    @property
    def n_short_segments(self) -> int:
        return int(np.count_nonzero(self.ends - self.starts < MIN_SEGMENT_POINTS))


def prepare(
    xyz: np.ndarray, t: np.ndarray, group: np.ndarray | None, p: ResolvedParameters
) -> SortedPoints:
    """Drop points without a finite time or position, sort, resolve max_gap, cut segments."""
    valid = finite_points(xyz, t)
    rows: np.ndarray | None = None if valid.all() else np.flatnonzero(valid)
    ts = t if rows is None else t[rows]
    gs = None if group is None else (group if rows is None else group[rows])
    order = _sort_order(ts, gs)
    if order is not None:
        rows = order if rows is None else rows[order]
        ts = ts[order]
        gs = None if gs is None else gs[order]
    z = np.empty((3, ts.size))
    for axis in range(3):
        z[axis] = xyz[:, axis] if rows is None else xyz[rows, axis]

    if ts.size == 0:
        g_bounds = np.zeros(1, dtype=np.int64)
    elif gs is None:
        g_bounds = np.array([0, ts.size], dtype=np.int64)
    else:
        g_bounds = np.r_[0, np.flatnonzero(gs[1:] != gs[:-1]) + 1, ts.size].astype(np.int64)
    gaps = np.empty(g_bounds.size - 1)
    gap_by_group: dict[int, float | None] = {}
    for g in range(gaps.size):
        start, end = g_bounds[g], g_bounds[g + 1]
        gid = 0 if gs is None else int(gs[start])
        value = p.max_gap if p.max_gap is not None else 5.0 * median_positive_step(ts[start:end])
        gaps[g] = value if math.isfinite(value) else math.inf  # no positive step: one segment
        gap_by_group[gid] = value if math.isfinite(value) else None
    starts, ends = cut_segments(ts, g_bounds, gaps)
    return SortedPoints(rows, ts, z, starts, ends, gap_by_group)


def unit_differences(
    s: SortedPoints, p: ResolvedParameters, compiled: bool | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """dz (m, 3) and sigma_dz (m,) of eqs. 15-16 with unit sigma; NaN where untested.
    ``compiled`` as in :func:`algorithms.temporal.windows.window_differences`."""
    return segment_differences(s.t, s.z, s.starts, s.ends, p.n1, p.n2, compiled=compiled)


def estimate_sigma(dz_unit: np.ndarray, sigma_dz_unit: np.ndarray,
                   floor: float | np.ndarray = 0.0) -> tuple[np.ndarray, str]:
    """Robust per-axis sigma from unit-sigma prediction differences, never below ``floor``
    (metres, one or per axis: the coordinates' rounding, :func:`algorithms.stats.rounding_sigma`).

    With one sigma per axis, eq. 17 is dz / (sigma * sigma_dz(unit)), so r = dz / sigma_dz(unit)
    has standard deviation sigma under H0; its MAD-based sigma ignores the outliers.
    dz_unit (m, 3), sigma_dz_unit (m,). Returns (3,) metres (NaN where nothing was tested) and
    how it was obtained ('mad', or 'std' when the MAD is 0, e.g. quantised straight lines).

    Above SIGMA_SAMPLE_POINTS tested points, the estimate uses an evenly strided subsample of
    that size (the MAD's sampling error is then ~0.4 %, and the medians stop dominating the
    detector's run time).
    """
    tested = np.flatnonzero(~np.isnan(sigma_dz_unit))
    if tested.size > SIGMA_SAMPLE_POINTS:
        tested = tested[:: -(-tested.size // SIGMA_SAMPLE_POINTS)]
    scale = sigma_dz_unit[tested]
    r = [dz_unit[:, j][tested] / scale for j in range(3)]  # column by column: no strided copies
    sigma = np.array([mad_sigma(r_j) for r_j in r])
    source = "mad"
    for j in range(3):
        if sigma[j] == 0.0:
            finite = r[j][np.isfinite(r[j])]
            spread = float(np.sqrt(np.mean(finite**2)))
            # All residuals zero: any positive sigma gives score 0.
            sigma[j] = spread if spread > 0 else 1.0
            source = "std"
    if np.any(sigma < floor):
        sigma, source = np.maximum(sigma, floor), f"{source}, raised to the coordinates' rounding"
    return sigma, source


def scores_from_differences(
    dz_unit: np.ndarray, sigma_dz_unit: np.ndarray, sigma: np.ndarray
) -> np.ndarray:
    """Score = max over axes of |eq. 17| for one sigma per axis (metres).

    dz_unit (m, 3), sigma_dz_unit (m,) from unit sigma; sigma (3,). Eq. 16 scales with sigma and
    the a_i do not depend on a common sigma, so eq. 17 = dz / (sigma * sigma_dz(unit)).
    NaN (untested) where sigma_dz_unit is NaN.
    """
    score = np.zeros(sigma_dz_unit.shape[0])
    for j, sigma_j in enumerate(np.asarray(sigma, dtype=np.float64)):
        np.maximum(score, np.abs(standardised_difference(dz_unit[:, j], sigma_j * sigma_dz_unit)),
                   out=score)
    return score


def detect_temporal(
    xyz: np.ndarray,
    gps_time: np.ndarray | None,
    group: np.ndarray | None = None,
    *,
    n1: int = 5,
    n2: int = 5,
    sigma: float | str | Sequence[float] = "auto",
    alpha: float = 0.001,
    max_gap: float | str = "auto",
    sigma_floor: float | Sequence[float] = 0.0,
) -> DetectorResult:
    """Algorithm (a): moving fixed-interval smoother outlier test (eqs. 1-17).

    Parameters
    ----------
    xyz : (n, 3) float64, coordinates in metres, any order.
    gps_time : (n,) float64, seconds. NaN entries (and points with non-finite xyz) are not tested
        and not used as neighbours.
    group : (n,) int or None, scanner id (e.g. point_source_id); each group is its own series.
    n1, n2 : points before / after the tested point in the window (n1 + n2 >= 3).
    sigma : metres, one number or one per axis (X, Y, Z), or "auto" (robust estimate per axis,
        see ``estimate_sigma``).
    alpha : two-sided significance level of the normal test of eq. 17.
    max_gap : seconds; a time step above it starts a new segment. "auto": 5 x the group's median
        positive time step.
    sigma_floor : metres, one or per axis: the least "auto" sigma (the coordinates' rounding,
        :func:`algorithms.stats.rounding_sigma`).

    Returns
    -------
    DetectorResult with score (n,) = max over X, Y, Z of |eq. 17| (NaN where untested: segments
    of fewer than 4 points, windows with fewer than three distinct times), flagged (n,) =
    score > normal_critical_value(alpha), and info with every resolved parameter.

    Examples
    --------
    >>> t = 5e5 + np.arange(60) * 1e-5
    >>> xyz = np.c_[5e6 + 300.0 * (t - 5e5), np.full(60, 3e5), np.full(60, 100.0)]
    >>> xyz[30, 2] += 0.1  # a 10-sigma spike: 10 / sqrt(eq. 16 / sigma^2) = 8.9
    >>> res = detect_temporal(xyz, t, sigma=0.01)
    >>> np.flatnonzero(res.flagged).tolist(), round(float(res.score[30]), 2)
    ([30], 8.9)
    """
    p = check_params(n1, n2, sigma, alpha, max_gap)
    xyz, t, group = check_arrays(xyz, gps_time, group)
    n = t.size
    if n and not np.isfinite(t).any():
        raise MissingDimensionError("gps_time is all NaN: the temporal detector cannot run")
    s = prepare(xyz, t, group, p)
    dz, sdz = unit_differences(s, p)
    if p.sigma is None:
        sigma_axes, source = estimate_sigma(dz, sdz, np.asarray(sigma_floor, dtype=np.float64))
    else:
        sigma_axes, source = p.sigma, "given"
    score_sorted = scores_from_differences(dz, sdz, sigma_axes)
    if s.rows is None:
        score = score_sorted
    else:
        score = np.full(n, np.nan)
        score[s.rows] = score_sorted
    flagged = score > p.critical_value
    info = result_info(p, sigma_axes, source, s.max_gap_by_group)
    info.update(
        points=int(n),
        points_tested=int(np.count_nonzero(~np.isnan(score))),
        points_flagged=int(np.count_nonzero(flagged)),
        segments=s.n_segments,
        segments_untested=s.n_short_segments,
    )
    return DetectorResult(score=score, flagged=flagged, critical_value=p.critical_value, info=info)


def _json_float(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def result_info(
    p: ResolvedParameters,
    sigma_axes: np.ndarray,
    source: str,
    gap_by_group: dict[int, float | None],
) -> dict:
    """A result's ``info``: the resolved parameters, sigma and max_gap (JSON-ready)."""
    gaps = [g for g in gap_by_group.values() if g is not None]
    info: dict = {
        "detector": "temporal",
        "n1": p.n1,
        "n2": p.n2,
        "alpha": p.alpha,
        "critical_value": p.critical_value,
        "sigma": {axis: _json_float(v) for axis, v in zip("xyz", sigma_axes, strict=True)},
        "sigma_source": source,
        "max_gap": p.max_gap if p.max_gap is not None else "auto",
        "max_gap_summary": {
            "min": min(gaps) if gaps else None,
            "median": float(np.median(gaps)) if gaps else None,
            "max": max(gaps) if gaps else None,
        },
        "groups": len(gap_by_group),
    }
    if len(gap_by_group) <= 256:
        info["max_gap_by_group"] = {str(g): v for g, v in gap_by_group.items()}
    return info
