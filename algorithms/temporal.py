"""The ``temporal`` detector: the paper's moving fixed-interval smoother (algorithm (a), eqs. 1-17).

Each scanner's points, ordered by GPS time and cut into line segments at time gaps, give three
series X(k), Y(k), Z(k). For every point k a quadratic in time (the alpha-beta-gamma state model,
eqs. 1-4) is fitted to the window [k - n1, k + n2]; eq. 15 predicts z(k) from the neighbours alone,
eq. 16 gives the variance of z(k) - z_p(k) and eq. 17 the standardised difference, which is tested
against the two-sided normal critical value. A point's score is the largest |eq. 17| of X, Y, Z.

Numerical care (GPS times near 5e5 s with steps near 1e-5 s, coordinates near 5e6 m):

- times enter only as delta = t_{k+i} - t_k (exact in float64 for neighbouring times), rescaled by
  the window's largest |delta| before the delta^4 sums are formed;
- coordinates enter only as z_{k+i} - z_k (the a_i of the neighbours sum to 1 - a_0, so eq. 15 is
  an affine combination and the reference z_k cancels exactly in exact arithmetic).

Layout: ``smoother_weights`` (eqs. 11, 14), ``predict_from_window`` (eq. 15),
``difference_variance`` (eq. 16) and ``standardised_difference`` (eq. 17) are the per-window
kernels; ``window_differences`` runs them over many points; ``detect_temporal`` is the batch
detector and ``TemporalStream`` the streaming one (identical results for fixed sigma and max_gap).
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from algorithms.result import DetectorResult
from algorithms.stats import mad_sigma, normal_critical_value
from worker.errors import MissingDimensionError, ParameterError

#: A segment shorter than this is not tested: three neighbours are the least that determine the
#: quadratic of eq. 15 and the point itself is the fourth.
MIN_SEGMENT_POINTS = 4

#: det(M) / (M_00 M_11 M_22) of the (rescaled) moment matrix of eq. 14 below which the window is
#: taken as singular (fewer than three distinct times). The ratio lies in [0, 1] (Hadamard).
_SINGULAR_RATIO = 1e-12

#: 1 - a_0(k) below this: the point itself carries the whole fit, eq. 15 is undefined.
_MIN_ONE_MINUS_A0 = 1e-10

#: Tested points above which ``estimate_sigma`` works on an evenly strided subsample.
SIGMA_SAMPLE_POINTS = 250_000

#: Points per parallel block in ``window_differences``, and the call size below which it runs
#: on one thread.
_BLOCK = 4096
_PARALLEL_POINTS = 8 * _BLOCK


# --------------------------------------------------------------------------------------------
# Per-window kernels (eqs. 11, 14-17)
# --------------------------------------------------------------------------------------------


@njit(cache=True)
def smoother_weights(delta: np.ndarray, weight: np.ndarray, out: np.ndarray, w: int) -> bool:
    """Smoother coefficients a_i(k) of eq. 11 with lambda from the inverse moment matrix of eq. 14.

    delta : (>= w,) float64, t_{k+i} - t_k for the window's w points (any time unit).
    weight : (>= w,) float64, 1 / sigma_{k+i}^2 (any common positive factor).
    out : (>= w,) float64, receives a_i(k) in window order. Only the first w entries are used
    (callers reuse buffers: slicing in the hot loop costs reference counting).

    Returns False (and leaves ``out`` undefined) when the moment matrix is singular, i.e. the
    window holds fewer than three distinct times. The a_i are invariant to rescaling delta by a
    time unit u (M -> D M D with D = diag(1, 1/u, 1/u^2), and D cancels in a_i) and to a common
    factor on the weights, so callers may pass delta / u and sigma in any unit.
    """
    s0 = 0.0
    s1 = 0.0
    s2 = 0.0
    s3 = 0.0
    s4 = 0.0
    for i in range(w):
        wi = weight[i]
        d = delta[i]
        d2 = d * d
        s0 += wi
        s1 += wi * d
        s2 += wi * d2
        s3 += wi * d2 * d
        s4 += wi * d2 * d2
    # First row of the inverse of the symmetric M = [[s0,s1,s2],[s1,s2,s3],[s2,s3,s4]] via
    # cofactors: (lambda_1, lambda_2, lambda_3) of eq. 14.
    c0 = s2 * s4 - s3 * s3
    c1 = s3 * s2 - s1 * s4
    c2 = s1 * s3 - s2 * s2
    det = s0 * c0 + s1 * c1 + s2 * c2
    if not det > _SINGULAR_RATIO * s0 * s2 * s4:
        return False
    lam1 = c0 / det
    lam2 = c1 / det
    lam3 = c2 / det
    for i in range(w):
        d = delta[i]
        out[i] = weight[i] * (lam1 + lam2 * d + lam3 * d * d)
    return True


@njit(cache=True)
def predict_from_window(
    a: np.ndarray, z: np.ndarray, start: int, w: int, k: int, out: np.ndarray
) -> None:
    """Eq. 15 for every column of z: out[j] = z_p(k) - z(k) for the window rows start:start+w.

    a : (>= w,) a_i(k) from ``smoother_weights``. z : (n, m) series. k : row of the tested point
    (start <= k < start + w). out : (m,) receives the predictions relative to z(k): the
    neighbours' a_i sum to 1 - a_0(k), so eq. 15 is an affine combination and subtracting the
    local reference z(k) first changes nothing but the rounding (coordinates near 5e6 m).
    """
    m = z.shape[1]
    centre = k - start
    for j in range(m):
        out[j] = 0.0
    for i in range(w):
        if i != centre:
            a_i = a[i]
            for j in range(m):
                out[j] += a_i * (z[start + i, j] - z[k, j])
    one_minus_a0 = 1.0 - a[centre]
    for j in range(m):
        out[j] /= one_minus_a0


@njit(cache=True)
def difference_variance(a: np.ndarray, variance: np.ndarray, w: int, centre: int) -> float:
    """Eq. 16: variance of z(k) - z_p(k).

    a : (>= w,) a_i(k). variance : (>= w,) sigma_{k+i}^2 (metres^2) of the window's w points.
    centre : position of k in the window.
    """
    acc = 0.0
    for i in range(w):
        if i != centre:
            acc += a[i] * a[i] * variance[i]
    one_minus_a0 = 1.0 - a[centre]
    return variance[centre] + acc / (one_minus_a0 * one_minus_a0)


@njit(cache=True)
def standardised_difference(dz: float, sigma_dz: float) -> float:
    """Eq. 17: dz / sigma_dz with dz = z(k) - z_p(k) and sigma_dz = sqrt(eq. 16).

    Standard normal under H0: dz = 0.
    """
    return dz / sigma_dz


@njit(cache=True)
def _differences_block(
    t: np.ndarray,
    z: np.ndarray,
    sigma: np.ndarray,
    targets: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    max_w: int,
    first: int,
    stop: int,
    dz: np.ndarray,
    sigma_dz: np.ndarray,
) -> None:
    """``window_differences`` for targets[first:stop], writing into dz and sigma_dz."""
    m = z.shape[1]
    unit_sigma = sigma.shape[0] == 0
    delta = np.empty(max_w)
    weight = np.ones(max_w)
    variance = np.ones(max_w)
    a = np.empty(max_w)
    pred = np.empty(m)
    for q in range(first, stop):
        k = targets[q]
        start = lo[q]
        w = hi[q] - start
        if w < MIN_SEGMENT_POINTS:
            continue
        t_k = t[k]
        # Per-window time unit (largest |delta|, t sorted in the window): keeps the delta^4
        # sums of eq. 14 near 1 whatever the time step.
        unit = max(t_k - t[start], t[start + w - 1] - t_k)
        if not unit > 0.0:
            continue
        inv_unit = 1.0 / unit
        for i in range(w):
            delta[i] = (t[start + i] - t_k) * inv_unit
        if not unit_sigma:
            for i in range(w):
                s = sigma[start + i]
                variance[i] = s * s
                weight[i] = 1.0 / variance[i]
        if not smoother_weights(delta, weight, a, w):
            continue
        if not 1.0 - a[k - start] > _MIN_ONE_MINUS_A0:
            continue
        predict_from_window(a, z, start, w, k, pred)
        for j in range(m):
            dz[q, j] = -pred[j]
        sigma_dz[q] = math.sqrt(difference_variance(a, variance, w, k - start))


@njit(cache=True, parallel=True)
def _differences_parallel(
    t: np.ndarray,
    z: np.ndarray,
    sigma: np.ndarray,
    targets: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    max_w: int,
    dz: np.ndarray,
    sigma_dz: np.ndarray,
) -> None:
    """``_differences_block`` over blocks of _BLOCK targets on all threads."""
    p = targets.shape[0]
    n_blocks = (p + _BLOCK - 1) // _BLOCK
    for b in prange(n_blocks):
        _differences_block(
            t, z, sigma, targets, lo, hi, max_w, b * _BLOCK, min(p, (b + 1) * _BLOCK), dz, sigma_dz
        )


def window_differences(
    t: np.ndarray,
    z: np.ndarray,
    sigma: np.ndarray,
    targets: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Eqs. 14-16 for many points, each with its own window.

    t : (n,) float64 times, non-decreasing within every window. z : (n, m) float64 series
    (m columns sharing the weights, e.g. X, Y, Z with one sigma per axis). sigma : (n,) float64
    per-point standard deviation, or (0,) for unit sigma everywhere (the detector's fast path).
    targets, lo, hi : (p,) int64; point ``targets[q]`` is predicted from rows lo[q]:hi[q]
    (which contain it).

    Returns dz (p, m) = z(k) - z_p(k) (eq. 15) and sigma_dz (p,) = sqrt(eq. 16); NaN for points
    whose window is degenerate (fewer than MIN_SEGMENT_POINTS rows or three distinct times, or
    a_0(k) = 1). Eq. 17 is dz / sigma_dz[:, None]. Every point is computed alone, so the result
    does not depend on how the points are split into calls or threads.
    """
    t = np.ascontiguousarray(t, dtype=np.float64)
    z = np.ascontiguousarray(z, dtype=np.float64)
    sigma = np.ascontiguousarray(sigma, dtype=np.float64)
    targets = np.ascontiguousarray(targets, dtype=np.int64)
    lo = np.ascontiguousarray(lo, dtype=np.int64)
    hi = np.ascontiguousarray(hi, dtype=np.int64)
    p = targets.size
    dz = np.full((p, z.shape[1]), np.nan)
    sigma_dz = np.full(p, np.nan)
    if p == 0:
        return dz, sigma_dz
    max_w = int(np.max(hi - lo))
    if p < _PARALLEL_POINTS:  # thread start-up costs more than it saves on small calls
        _differences_block(t, z, sigma, targets, lo, hi, max_w, 0, p, dz, sigma_dz)
    else:
        _differences_parallel(t, z, sigma, targets, lo, hi, max_w, dz, sigma_dz)
    return dz, sigma_dz


# --------------------------------------------------------------------------------------------
# Segments and windows
# --------------------------------------------------------------------------------------------


def window_bounds(
    position: np.ndarray, seg_start: np.ndarray, seg_end: np.ndarray, n1: int, n2: int
) -> tuple[np.ndarray, np.ndarray]:
    """Window rows [lo, hi) of each point: [k - n1, k + n2] shifted inside its segment.

    All arguments (p,) int64 row numbers; the segment of a point is rows seg_start:seg_end. The
    window keeps n1 + n2 neighbours when the segment holds that many (the paper's "window size
    adjusted at the start and end of each line"), otherwise it is the whole segment.
    """
    size = n1 + n2 + 1
    lo = np.minimum(np.maximum(position - n1, seg_start), seg_end - size)
    short = seg_end - seg_start < size
    lo = np.where(short, seg_start, lo)
    hi = np.where(short, seg_end, lo + size)
    return lo, hi


@njit(cache=True)
def segment_windows(
    t: np.ndarray, group_bounds: np.ndarray, max_gap: np.ndarray, n1: int, n2: int
) -> tuple[np.ndarray, np.ndarray, int, int]:
    """Cut sorted groups into segments at time gaps and give every row its window.

    t : (n,) times sorted within each group; group g is rows group_bounds[g]:group_bounds[g+1].
    max_gap : (g,) seconds per group; a step t[r] - t[r-1] > max_gap starts a new segment.
    Returns lo, hi (n,) int64 window rows (as ``window_bounds``), the number of segments and the
    number of segments shorter than MIN_SEGMENT_POINTS (their rows stay untested).
    """
    n = t.shape[0]
    size = n1 + n2 + 1
    lo = np.empty(n, dtype=np.int64)
    hi = np.empty(n, dtype=np.int64)
    n_segments = 0
    n_short = 0
    for g in range(group_bounds.shape[0] - 1):
        g_start = group_bounds[g]
        g_end = group_bounds[g + 1]
        s = g_start
        for r in range(g_start + 1, g_end + 1):
            if r < g_end and not t[r] - t[r - 1] > max_gap[g]:
                continue
            n_segments += 1
            if r - s < MIN_SEGMENT_POINTS:
                n_short += 1
            for k in range(s, r):
                if r - s < size:
                    lo[k] = s
                    hi[k] = r
                else:
                    lo[k] = min(max(k - n1, s), r - size)
                    hi[k] = lo[k] + size
            s = r
    return lo, hi, n_segments, n_short


@njit(cache=True)
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
    targets = np.empty(n, dtype=np.int64)
    lo = np.empty(n, dtype=np.int64)
    hi = np.empty(n, dtype=np.int64)
    count = 0
    n_segments = 0
    n_short = 0
    for r in range(1, n + 1):
        if r < n and not t[r] - t[r - 1] > max_gap:
            continue
        first = max(done, seg_start)
        if r < n or final:  # segment [seg_start, r) is closed
            for k in range(first, r):
                targets[count] = k
                if r - seg_start < size:
                    lo[count] = seg_start
                    hi[count] = r
                else:
                    lo[count] = min(max(k - n1, seg_start), r - size)
                    hi[count] = lo[count] + size
                count += 1
            n_segments += 1
            if r - seg_start < MIN_SEGMENT_POINTS:
                n_short += 1
            done = r
            seg_start = r
        else:  # the open segment [seg_start, n)
            done = first
            if n - seg_start >= size:
                for k in range(first, n - n2):
                    targets[count] = k
                    lo[count] = max(k - n1, seg_start)
                    hi[count] = lo[count] + size
                    count += 1
                    done = k + 1
    return targets[:count], lo[:count], hi[:count], done, seg_start, n_segments, n_short


def _median_positive_step(t: np.ndarray) -> float:
    """Median of the positive steps of a sorted time series; NaN if it has none."""
    dt = np.diff(t)
    dt = dt[dt > 0]
    return float(np.median(dt)) if dt.size else math.nan


# --------------------------------------------------------------------------------------------
# Parameters
# --------------------------------------------------------------------------------------------


@dataclass
class _Params:
    n1: int
    n2: int
    alpha: float
    critical_value: float
    sigma: np.ndarray | None  # (3,) metres, None for "auto"
    max_gap: float | None  # seconds, None for "auto"


def _check_params(
    n1: int, n2: int, sigma: float | str | Sequence[float], alpha: float, max_gap: float | str
) -> _Params:
    for name, value in (("n1", n1), ("n2", n2)):
        if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 1:
            raise ParameterError(f"{name} must be an integer >= 1, got {value!r}")
    if n1 + n2 < 3:
        raise ParameterError(
            f"n1 + n2 must be >= 3 (a quadratic needs three neighbours to predict a point), "
            f"got n1={n1}, n2={n2}"
        )
    if isinstance(alpha, bool) or not isinstance(alpha, numbers.Real) or not 0.0 < alpha < 0.5:
        raise ParameterError(f"alpha must be in (0, 0.5), got {alpha!r}")
    sigma_arr: np.ndarray | None = None
    if isinstance(sigma, str):
        if sigma != "auto":
            raise ParameterError(f"sigma must be a number > 0 or 'auto', got {sigma!r}")
    else:
        try:
            sigma_arr = np.broadcast_to(np.asarray(sigma, dtype=np.float64), (3,)).copy()
        except (TypeError, ValueError):
            raise ParameterError(
                f"sigma must be a number > 0, three numbers or 'auto', got {sigma!r}"
            ) from None
        if not np.all(np.isfinite(sigma_arr) & (sigma_arr > 0)):
            raise ParameterError(f"sigma must be > 0 and finite, got {sigma!r}")
    gap: float | None = None
    if isinstance(max_gap, str):
        if max_gap != "auto":
            raise ParameterError(f"max_gap must be a number > 0 or 'auto', got {max_gap!r}")
    else:
        try:
            gap = float(max_gap)
        except (TypeError, ValueError):
            raise ParameterError(
                f"max_gap must be a number > 0 or 'auto', got {max_gap!r}"
            ) from None
        if not gap > 0:
            raise ParameterError(f"max_gap must be > 0 or 'auto', got {max_gap!r}")
    return _Params(int(n1), int(n2), float(alpha), normal_critical_value(alpha), sigma_arr, gap)


def _check_arrays(
    xyz: np.ndarray, gps_time: np.ndarray | None, group: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    if gps_time is None:
        raise MissingDimensionError("the temporal detector needs gps_time, which this data lacks")
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ParameterError(f"xyz must have shape (n, 3), got {xyz.shape}")
    t = np.asarray(gps_time, dtype=np.float64)
    if t.shape != (xyz.shape[0],):
        raise ParameterError(f"gps_time must have shape ({xyz.shape[0]},), got {t.shape}")
    if group is not None:
        group = np.asarray(group)
        if group.shape != t.shape:
            raise ParameterError(f"group must have shape ({t.size},), got {group.shape}")
        if not np.issubdtype(group.dtype, np.integer):
            raise ParameterError(f"group must hold integers (scanner ids), got {group.dtype}")
    return xyz, t, group


# --------------------------------------------------------------------------------------------
# Batch detector
# --------------------------------------------------------------------------------------------


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


@dataclass
class _Sorted:
    """Valid points in (group, time) order with their windows."""

    rows: np.ndarray | None  # (m,) original row of each sorted point; None: identity, m = n
    t: np.ndarray  # (m,)
    xyz: np.ndarray  # (m, 3) C-contiguous
    lo: np.ndarray  # (m,) window rows [lo, hi)
    hi: np.ndarray
    n_segments: int
    n_short_segments: int
    max_gap_by_group: dict[int, float | None]


def _prepare(xyz: np.ndarray, t: np.ndarray, group: np.ndarray | None, p: _Params) -> _Sorted:
    """Drop points without a finite time or position, sort, resolve max_gap, cut windows."""
    valid = np.isfinite(t) & np.isfinite(xyz).all(axis=1)
    rows: np.ndarray | None = None if valid.all() else np.flatnonzero(valid)
    ts = t if rows is None else t[rows]
    gs = None if group is None else (group if rows is None else group[rows])
    order = _sort_order(ts, gs)
    if order is not None:
        rows = order if rows is None else rows[order]
        ts = ts[order]
        gs = None if gs is None else gs[order]
    xyz_s = np.ascontiguousarray(xyz if rows is None else xyz[rows])

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
        value = p.max_gap if p.max_gap is not None else 5.0 * _median_positive_step(ts[start:end])
        gaps[g] = value if math.isfinite(value) else math.inf  # no positive step: one segment
        gap_by_group[gid] = value if math.isfinite(value) else None
    lo, hi, n_segments, n_short = segment_windows(ts, g_bounds, gaps, p.n1, p.n2)
    return _Sorted(rows, ts, xyz_s, lo, hi, int(n_segments), int(n_short), gap_by_group)


def _unit_differences(s: _Sorted) -> tuple[np.ndarray, np.ndarray]:
    """dz (m, 3) and sigma_dz (m,) of eqs. 15-16 with unit sigma; NaN where untested."""
    targets = np.arange(s.t.size, dtype=np.int64)
    return window_differences(s.t, s.xyz, np.empty(0), targets, s.lo, s.hi)


def estimate_sigma(dz_unit: np.ndarray, sigma_dz_unit: np.ndarray) -> tuple[np.ndarray, str]:
    """Robust per-axis sigma from unit-sigma prediction differences.

    With one sigma per axis, eq. 17 is dz / (sigma * sigma_dz(unit)), so r = dz / sigma_dz(unit)
    has standard deviation sigma under H0; its MAD-based sigma ignores the outliers.
    dz_unit (m, 3), sigma_dz_unit (m,). Returns (3,) metres (NaN where nothing was tested) and
    how it was obtained ('mad', or 'std' when the MAD is 0, e.g. quantised straight lines).

    Above SIGMA_SAMPLE_POINTS tested points, the estimate uses an evenly strided subsample of
    that size (the MAD's sampling error is then ~0.3 %, and the medians stop dominating the
    detector's run time).
    """
    tested = np.flatnonzero(~np.isnan(sigma_dz_unit))
    if tested.size > SIGMA_SAMPLE_POINTS:
        tested = tested[:: -(-tested.size // SIGMA_SAMPLE_POINTS)]
    r = dz_unit[tested] / sigma_dz_unit[tested, None]
    sigma = np.array([mad_sigma(r[:, j]) for j in range(3)])
    source = "mad"
    for j in range(3):
        if sigma[j] == 0.0:
            finite = r[np.isfinite(r[:, j]), j]
            spread = float(np.sqrt(np.mean(finite**2)))
            # All residuals zero: any positive sigma gives score 0.
            sigma[j] = spread if spread > 0 else 1.0
            source = "std"
    return sigma, source


@njit(cache=True)
def scores_from_differences(
    dz_unit: np.ndarray, sigma_dz_unit: np.ndarray, sigma: np.ndarray
) -> np.ndarray:
    """Score = max over axes of |eq. 17| for one sigma per axis (metres).

    dz_unit (m, 3), sigma_dz_unit (m,) from unit sigma; sigma (3,). Eq. 16 scales with sigma and
    the a_i do not depend on a common sigma, so eq. 17 = dz / (sigma * sigma_dz(unit)).
    NaN (untested) where sigma_dz_unit is NaN.
    """
    n = dz_unit.shape[0]
    score = np.full(n, np.nan)
    for k in range(n):
        if not np.isnan(sigma_dz_unit[k]):
            best = 0.0
            for j in range(dz_unit.shape[1]):
                z = standardised_difference(dz_unit[k, j], sigma[j] * sigma_dz_unit[k])
                best = max(best, abs(z))
            score[k] = best
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
    p = _check_params(n1, n2, sigma, alpha, max_gap)
    xyz, t, group = _check_arrays(xyz, gps_time, group)
    n = t.size
    if n and not np.isfinite(t).any():
        raise MissingDimensionError("gps_time is all NaN: the temporal detector cannot run")
    s = _prepare(xyz, t, group, p)
    dz, sdz = _unit_differences(s)
    if p.sigma is None:
        sigma_axes, source = estimate_sigma(dz, sdz)
    else:
        sigma_axes, source = p.sigma, "given"
    score_sorted = scores_from_differences(dz, sdz, sigma_axes)
    if s.rows is None:
        score = score_sorted
    else:
        score = np.full(n, np.nan)
        score[s.rows] = score_sorted
    flagged = score > p.critical_value
    info = _info(p, sigma_axes, source, s.max_gap_by_group)
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


def _info(
    p: _Params, sigma_axes: np.ndarray, source: str, gap_by_group: dict[int, float | None]
) -> dict:
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


# --------------------------------------------------------------------------------------------
# Streaming detector
# --------------------------------------------------------------------------------------------


@dataclass
class _Tail:
    """What a stream keeps of one group: the open segment's last rows.

    Rows [0, n_done) were scored already and stay only as window context (at most n1 + n2 of
    them); rows [n_done, len) wait for their window to complete. ``seg_pos0`` is the position of
    row 0 in its segment (the segment may have begun in an earlier chunk).
    """

    t: np.ndarray
    xyz: np.ndarray
    index: np.ndarray
    seg_pos0: int = 0
    n_done: int = 0
    max_gap: float | None = None  # seconds; None while 'auto' is unresolved


def _split_by_group(rows: np.ndarray, group: np.ndarray | None) -> dict[int, np.ndarray]:
    """rows (r,) split by their group id, each part keeping the input order (stable sort)."""
    if group is None:
        return {0: rows} if rows.size else {}
    g = group[rows]
    order = np.argsort(g, kind="stable")
    g, rows = g[order], rows[order]
    cuts = np.flatnonzero(g[1:] != g[:-1]) + 1
    parts = np.split(rows, cuts)
    return {int(g[a]): part for a, part in zip(np.r_[0, cuts], parts, strict=True) if part.size}


class TemporalStream:
    """The ``temporal`` detector over a stream of chunks, with memory bounded per group.

    Feed successive chunks with ``push`` (points ordered by time within each group; groups may
    interleave, chunks may have any size) and call ``finish`` at the end. Both return
    ``(index, score)`` for the points whose score became final, in no particular order: a point
    is final once its window is complete (n2 later points of its segment have arrived and the
    segment is long enough) or its segment ended at a time gap. Points without a finite time or
    position come back at once with score NaN. ``critical_value`` gives the flag threshold.

    With numeric ``sigma`` and ``max_gap`` the scores equal ``detect_temporal`` on the
    concatenated input exactly. With ``'auto'`` either is resolved from the first
    ``warmup_points`` points (at least the first chunk; all of them if the stream is shorter),
    which are held back until then: sigma as in ``detect_temporal`` on those points, max_gap
    per group from that group's points among them (a group first seen later: from its first
    rows that hold a positive time step). The resolved values are in ``info``.
    """

    def __init__(
        self,
        *,
        n1: int = 5,
        n2: int = 5,
        sigma: float | str | Sequence[float] = "auto",
        alpha: float = 0.001,
        max_gap: float | str = "auto",
        warmup_points: int = 200_000,
    ) -> None:
        self._p = _check_params(n1, n2, sigma, alpha, max_gap)
        if isinstance(warmup_points, bool) or not isinstance(warmup_points, int | np.integer):
            raise ParameterError(f"warmup_points must be an integer, got {warmup_points!r}")
        self._warmup_points = int(warmup_points)
        self._size = self._p.n1 + self._p.n2 + 1
        self._sigma: np.ndarray | None = self._p.sigma
        self._sigma_source = "given" if self._sigma is not None else "auto"
        self._resolved = self._sigma is not None and self._p.max_gap is not None
        self._warmup: list[tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray]] = []
        self._warmup_count = 0
        self._tails: dict[int, _Tail] = {}
        self._gap_by_group: dict[int, float | None] = {}
        self._counts = {"points": 0, "points_tested": 0, "points_flagged": 0}
        self._segments = 0
        self._short_segments = 0
        self._finished = False

    @property
    def critical_value(self) -> float:
        """Two-sided normal critical value for alpha: a point is flagged when score > this."""
        return self._p.critical_value

    @property
    def info(self) -> dict:
        """Resolved parameters and counts so far (JSON-serialisable), as ``detect_temporal``."""
        sigma = self._sigma if self._sigma is not None else np.full(3, np.nan)
        info = _info(self._p, sigma, self._sigma_source, self._gap_by_group)
        info.update(self._counts, segments=self._segments, segments_untested=self._short_segments)
        return info

    def push(
        self,
        xyz: np.ndarray,
        gps_time: np.ndarray,
        group: np.ndarray | None,
        index: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Add a chunk: xyz (c, 3), gps_time (c,), group (c,) ints or None, index (c,) ints.

        Returns (index, score) of the points that became final, as int64 and float64 arrays.
        """
        if self._finished:
            raise ParameterError("this TemporalStream is finished; start a new one")
        xyz, t, group = _check_arrays(xyz, gps_time, group)
        index = np.asarray(index)
        if index.shape != t.shape or not np.issubdtype(index.dtype, np.integer):
            raise ParameterError(f"index must hold ({t.size},) integers, got {index.shape}")
        if not self._resolved:
            self._warmup.append((xyz, t, group, index))
            self._warmup_count += t.size
            if self._warmup_count < self._warmup_points:
                return np.zeros(0, dtype=np.int64), np.zeros(0)
            return self._end_warmup(final=False)
        return self._process(xyz, t, group, index, final=False)

    def finish(self) -> tuple[np.ndarray, np.ndarray]:
        """Flush every held-back point (the open segments end here)."""
        if self._finished:
            return np.zeros(0, dtype=np.int64), np.zeros(0)
        if not self._resolved:
            out = self._end_warmup(final=True)
        else:
            out = self._process(np.zeros((0, 3)), np.zeros(0), None, np.zeros(0, np.int64), True)
        self._finished = True
        return out

    # -- internals ---------------------------------------------------------------------------

    def _end_warmup(self, final: bool) -> tuple[np.ndarray, np.ndarray]:
        """Resolve 'auto' sigma / max_gap from the held-back points, then process them."""
        chunks = self._warmup
        self._warmup = []
        xyz = np.concatenate([c[0] for c in chunks])
        t = np.concatenate([c[1] for c in chunks])
        has_group = any(c[2] is not None for c in chunks)
        group = None
        if has_group:
            group = np.concatenate(
                [c[2] if c[2] is not None else np.zeros(c[1].size, np.int64) for c in chunks]
            )
        index = np.concatenate([c[3] for c in chunks])
        s = _prepare(xyz, t, group, self._p)
        if self._p.max_gap is None:
            self._gap_by_group.update(s.max_gap_by_group)
            for gid, gap in s.max_gap_by_group.items():
                if gap is not None:
                    self._tail(gid).max_gap = gap
        if self._sigma is None:
            dz, sdz = _unit_differences(s)
            self._sigma, self._sigma_source = estimate_sigma(dz, sdz)
        self._resolved = True
        return self._process(xyz, t, group, index, final)

    def _tail(self, gid: int) -> _Tail:
        if gid not in self._tails:
            self._tails[gid] = _Tail(
                np.zeros(0), np.zeros((0, 3)), np.zeros(0, np.int64), max_gap=self._p.max_gap
            )
        return self._tails[gid]

    def _process(
        self,
        xyz: np.ndarray,
        t: np.ndarray,
        group: np.ndarray | None,
        index: np.ndarray,
        final: bool,
    ) -> tuple[np.ndarray, np.ndarray]:
        out_index: list[np.ndarray] = []
        out_score: list[np.ndarray] = []
        valid = np.isfinite(t) & np.isfinite(xyz).all(axis=1)
        if not valid.all():
            out_index.append(index[~valid].astype(np.int64))
            out_score.append(np.full(int(np.count_nonzero(~valid)), np.nan))
        rows_by_group = _split_by_group(np.flatnonzero(valid), group)
        for gid in sorted(set(rows_by_group) | (set(self._tails) if final else set())):
            rows = rows_by_group.get(gid, np.zeros(0, dtype=np.int64))
            tail = self._tail(gid)
            idx, score = self._advance(gid, tail, t[rows], xyz[rows], index[rows], final)
            out_index.append(idx)
            out_score.append(score)
            if final:
                del self._tails[gid]
        if not out_index:
            return np.zeros(0, dtype=np.int64), np.zeros(0)
        idx = np.concatenate(out_index).astype(np.int64, copy=False)
        score = np.concatenate(out_score)
        self._counts["points"] += idx.size
        self._counts["points_tested"] += int(np.count_nonzero(~np.isnan(score)))
        self._counts["points_flagged"] += int(np.count_nonzero(score > self.critical_value))
        return idx, score

    def _advance(
        self,
        gid: int,
        tail: _Tail,
        t_new: np.ndarray,
        xyz_new: np.ndarray,
        idx_new: np.ndarray,
        final: bool,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Append one group's rows, score the rows whose windows are complete, trim the tail."""
        t = np.concatenate([tail.t, t_new])
        if np.any(t[1:] < t[:-1]):
            raise ParameterError(
                "TemporalStream needs points ordered by gps_time within each group"
            )
        xyz = np.concatenate([tail.xyz, xyz_new])
        index = np.concatenate([tail.index, idx_new.astype(np.int64)])
        if tail.max_gap is None:
            step = _median_positive_step(t)
            if not math.isfinite(step) and not final:
                tail.t, tail.xyz, tail.index = t, xyz, index  # cannot cut segments yet
                return np.zeros(0, dtype=np.int64), np.zeros(0)
            tail.max_gap = 5.0 * step if math.isfinite(step) else math.inf
        if gid not in self._gap_by_group:
            self._gap_by_group[gid] = tail.max_gap if math.isfinite(tail.max_gap) else None

        targets, lo, hi, done, seg_start, n_seg, n_short = stream_windows(
            t, tail.max_gap, -tail.seg_pos0, tail.n_done, self._p.n1, self._p.n2, final
        )
        self._segments += n_seg
        self._short_segments += n_short
        score = np.zeros(0)
        if targets.size:
            dz, sdz = window_differences(t, xyz, np.empty(0), targets, lo, hi)
            score = scores_from_differences(dz, sdz, self._sigma)
        # Keep the open segment's pending rows and up to n1 + n2 rows of context before them.
        n = t.size
        keep = n if final else max(0, seg_start, done - (self._size - 1))
        tail.t, tail.xyz, tail.index = t[keep:], xyz[keep:], index[keep:]
        tail.seg_pos0 = keep - seg_start
        tail.n_done = done - keep
        return index[targets], score
