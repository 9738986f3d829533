"""The ``temporal`` detector: the paper's moving fixed-interval smoother (algorithm (a), eqs. 1-17).

Each scanner's points, ordered by GPS time and cut into line segments at time gaps, give three
series X(k), Y(k), Z(k). For every point k a quadratic in time (the alpha-beta-gamma state model,
eqs. 1-4) is fitted to the window [k - n1, k + n2]; eq. 15 predicts z(k) from the neighbours alone,
eq. 16 gives the variance of z(k) - z_p(k) and eq. 17 the standardised difference, which is tested
against the two-sided normal critical value. A point's score is the largest |eq. 17| of X, Y, Z.

Numerical care (GPS times near 5e5 s with steps near 1e-5 s, coordinates near 5e6 m):

- times enter only as delta = t_{k+i} - t_k (exact in float64 for neighbouring times), rescaled by
  the window's largest |delta|, and the fit uses polynomials orthogonal over the window instead
  of inverting the moment matrix of eq. 14 (``smoother_weights``);
- coordinates enter only as z_{k+i} - z_k (the a_i of the neighbours sum to 1 - a_0, so eq. 15 is
  an affine combination and the reference z_k cancels exactly in exact arithmetic).

Layout: ``smoother_weights`` (eqs. 11, 14), ``predict_from_window`` (eq. 15),
``difference_variance`` (eq. 16) and ``standardised_difference`` (eq. 17) are the kernels, each
vectorised over a block of windows (plain numpy: no compilation, so a short command does not
pay for numba's start-up); ``window_differences`` (any windows) and ``segment_differences``
(every row of cut segments) run them block by block on all cores; ``detect_temporal`` is the
batch detector and ``TemporalStream`` the streaming one (identical results for fixed sigma and
max_gap).
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np

from algorithms.errors import MissingDimensionError, ParameterError
from algorithms.params import Parameters, param
from algorithms.result import DetectorResult
from algorithms.stats import mad_sigma, normal_critical_value

#: A segment shorter than this is not tested: three neighbours are the least that determine the
#: quadratic of eq. 15 and the point itself is the fourth.
MIN_SEGMENT_POINTS = 4

#: N_2 / N_0 (the weighted mean square of the second orthogonal polynomial, times scaled to
#: [-1, 1]) below which the window is taken as singular: fewer than three distinct times.
_SINGULAR_RATIO = 1e-12

#: 1 - a_0(k) below this: the point itself carries the whole fit, eq. 15 is undefined.
_MIN_ONE_MINUS_A0 = 1e-10

#: Tested points above which ``estimate_sigma`` works on an evenly strided subsample.
SIGMA_SAMPLE_POINTS = 100_000

#: Windows per block (a block's temporaries of this length stay near the CPU), and the number
#: of windows below which ``_differences`` runs on one thread.
_BLOCK = 16384
_PARALLEL_POINTS = 2 * _BLOCK

#: Shortest run of alike consecutive windows that ``window_differences`` serves by slices.
_MIN_RUN = 64


@dataclass(frozen=True)
class TemporalParameters(Parameters):
    """Algorithm (a): moving fixed-interval smoother along scan lines (eqs. 1-17)."""

    n1: int = param(5, "Points before the tested point in the window.", ge=1, le=100)
    n2: int = param(5, "Points after the tested point in the window.", ge=1, le=100)
    sigma: float | tuple[float, float, float] | Literal["auto"] = param(
        "auto", "Standard deviation of each coordinate in metres (> 0; one number or one per "
        "axis X, Y, Z), or 'auto' for a robust estimate from the data (reported in the "
        "statistics).", gt=0)
    alpha: float = param(0.001, "Two-sided significance level.", gt=0, lt=0.5)
    max_gap: float | Literal["auto"] = param(
        "auto", "Time step in seconds (> 0) above which a scan line is split into segments; "
        "'auto' = 5 x the group's median positive time step.", gt=0)
    group_by: Literal["point_source_id", "none"] = param(
        "point_source_id", "Dimension that separates the scanners, or 'none'.")

    def check(self) -> None:
        if self.n1 + self.n2 < 3:
            # A quadratic in time (eqs. 1-3) needs three neighbours besides the tested point,
            # otherwise the point carries the whole fit and eq. 15 divides by zero.
            raise ParameterError(
                f"n1 + n2 must be >= 3 (a quadratic needs three neighbours to predict a point), "
                f"got n1={self.n1}, n2={self.n2}")


# --------------------------------------------------------------------------------------------
# Per-window kernels (eqs. 11, 14-17), each vectorised over a block of windows
# --------------------------------------------------------------------------------------------


@dataclass
class WindowBlock:
    """b windows of w rows each as (w, b) arrays: column q holds the q-th window.

    ``t`` (w, b) times, ``z`` (m, w, b) series, ``weight`` (w, b) 1 / sigma^2 of the rows (0 for
    padding, when a window is shorter than w; its rows repeat the window's last row) or None
    for unit sigma everywhere. ``t_k``, ``z_k`` (m, b) and ``variance_k`` (None: 1) belong to the
    tested points. ``t[0]`` and ``t[-1]`` are each window's first and last time.
    """

    t: np.ndarray
    z: np.ndarray
    weight: np.ndarray | None
    t_k: np.ndarray
    z_k: np.ndarray
    variance_k: np.ndarray | None


def _sum_rows(x: np.ndarray, axis: int = 0) -> np.ndarray:
    """Sum over the window rows (``axis``) in row order, the same order in every block (numpy's
    own reductions may sum pairwise for some shapes, which would change the last bits)."""
    rows = np.moveaxis(x, axis, 0)
    total = rows[0].copy()
    for row in rows[1:]:
        total += row
    return total


def smoother_weights(block: WindowBlock) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Smoother coefficients a_i(k) of eq. 11 (lambda of eq. 14), by orthogonal polynomials.

    Returns (a, a_0, usable): a (w, b) for every window row (0 for padding), a_0(k) (b,) the
    tested point's own coefficient, and usable (b,) False where the window holds fewer than
    three distinct times or a_0(k) is 1 (the point carries the whole fit).

    Eq. 11 with lambda = M^-1 e_1 (eq. 14) is the least-squares quadratic's hat matrix,
    a_i = w_i p_i^T M^-1 p_k with p = (1, delta, delta^2), and the hat matrix does not depend on
    the polynomial basis. Inverting M itself (condition number up to 1e4 and more with
    uneven weights) loses digits; in the basis of Forsythe's polynomials, orthogonal over the
    window's weighted points (q_0 = 1, q_1 = delta - alpha_1, q_2 = (delta - alpha_2) q_1 -
    beta_1), M is diagonal (N_0, N_1, N_2) and a_i = w_i sum_j q_j(i) q_j(k) / N_j exactly.

    Times enter as delta = (t_{k+i} - t_k) / u with u the window's largest |delta|; the a_i do
    not depend on u nor on a common factor of the weights.
    """
    weight = block.weight

    def weighted_sum(x: np.ndarray) -> np.ndarray:
        return _sum_rows(x if weight is None else weight * x)

    inv_unit = 1.0 / np.maximum(block.t_k - block.t[0], block.t[-1] - block.t_k)
    q1 = np.subtract(block.t, block.t_k, out=np.empty(block.t.shape))  # delta, then q_1
    q1 *= inv_unit
    n0 = np.full(block.t_k.size, float(q1.shape[0])) if weight is None else _sum_rows(weight)
    alpha1 = weighted_sum(q1) / n0
    q1 -= alpha1
    power = q1 * q1
    n1 = weighted_sum(power)
    power *= q1
    gamma, beta1 = weighted_sum(power) / n1, n1 / n0  # alpha_2 - alpha_1 and beta_1
    q2 = np.subtract(q1, gamma, out=power)
    q2 *= q1
    q2 -= beta1
    n2 = weighted_sum(q2 * q2)
    q1_k = -alpha1  # delta_k = 0
    q2_k = (q1_k - gamma) * q1_k - beta1
    c1, c2 = q1_k / n1, q2_k / n2
    a = q1  # w_i (1 / N_0 + c_1 q_1(i) + c_2 q_2(i)), in place of q_1
    a *= c1
    a += 1.0 / n0
    q2 *= c2
    a += q2
    if weight is not None:
        a *= weight
    a_0 = 1.0 / n0 + c1 * q1_k + c2 * q2_k
    if block.variance_k is not None:
        a_0 /= block.variance_k
    usable = n2 > _SINGULAR_RATIO * n0
    usable &= 1.0 - a_0 > _MIN_ONE_MINUS_A0
    return a, a_0, usable


def predict_from_window(block: WindowBlock, a: np.ndarray, a_0: np.ndarray) -> np.ndarray:
    """Eq. 15 relative to the tested point: z_p(k) - z(k), (m, b).

    The neighbours' a_i sum to 1 - a_0(k), so eq. 15 is an affine combination and subtracting
    the local reference z(k) first changes nothing but the rounding (coordinates near 5e6 m).
    The tested point's own row adds a_0 (z(k) - z(k)) = 0, so it needs no exclusion.
    """
    term = np.subtract(block.z, block.z_k[:, None, :], out=np.empty(block.z.shape))
    term *= a
    prediction = _sum_rows(term, axis=1)
    prediction /= 1.0 - a_0
    return prediction


def difference_variance(block: WindowBlock, a_0: np.ndarray) -> np.ndarray:
    """Eq. 16, the variance of z(k) - z_p(k): sigma_k^2 + sum_{i!=k} a_i^2 sigma_i^2 / (1 - a_0)^2.

    With weights 1 / sigma_i^2 the sum collapses: a_i^2 sigma_i^2 = w_i (lambda . p_i)^2 with
    p_i = (1, delta_i, delta_i^2), whose sum over the whole window is lambda^T M lambda =
    lambda_1 (M lambda = e_1, eq. 14), and the point's own term is w_k lambda_1^2 = a_0 lambda_1.
    So eq. 16 = sigma_k^2 + lambda_1 / (1 - a_0) = sigma_k^2 / (1 - a_0): the leave-one-out
    variance of a least-squares smoother (a_0 is its hat-matrix diagonal). The tests check it
    against the literal sum.
    """
    variance_k = 1.0 if block.variance_k is None else block.variance_k
    return variance_k / (1.0 - a_0)


def standardised_difference(dz: np.ndarray, sigma_dz: np.ndarray) -> np.ndarray:
    """Eq. 17: dz / sigma_dz with dz = z(k) - z_p(k) and sigma_dz = sqrt(eq. 16).

    Standard normal under H0: dz = 0.
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        return dz / sigma_dz


def _block_differences(block: WindowBlock) -> tuple[np.ndarray, np.ndarray]:
    """dz (m, b) = z(k) - z_p(k) (eq. 15) and sigma_dz (b,) = sqrt(eq. 16); NaN if unusable."""
    with np.errstate(divide="ignore", invalid="ignore"):  # unusable windows, masked below
        a, a_0, usable = smoother_weights(block)
        dz = predict_from_window(block, a, a_0)
        np.negative(dz, out=dz)
        sigma_dz = np.sqrt(difference_variance(block, a_0))
    dz[:, ~usable] = np.nan
    sigma_dz[~usable] = np.nan
    return dz, sigma_dz


# --------------------------------------------------------------------------------------------
# Many windows: blocks of slices or of gathered rows, on all threads
# --------------------------------------------------------------------------------------------


def _sliced_block(
    t: np.ndarray, z: np.ndarray, sigma: np.ndarray, first: int, stop: int, centre: int, w: int
) -> WindowBlock:
    """Windows of rows k in [first, stop), each rows k - centre to k - centre + w - 1 (views).

    t (n,), z (m, n), sigma (n,) or (0,) for unit sigma.
    """
    rows = slice(first - centre, stop - centre + w - 1)

    def windows(x: np.ndarray) -> np.ndarray:  # (..., w, b) view: [..., i, q] = x[..., row q + i]
        return np.swapaxes(np.lib.stride_tricks.sliding_window_view(x[..., rows], w, axis=-1),
                           -1, -2)

    unit = sigma.size == 0
    variance = None if unit else sigma * sigma
    return WindowBlock(
        t=windows(t),
        z=windows(z),
        weight=None if unit else 1.0 / windows(variance),
        t_k=t[first:stop],
        z_k=z[:, first:stop],
        variance_k=None if unit else variance[first:stop],
    )


def _gathered_block(
    t: np.ndarray, z: np.ndarray, sigma: np.ndarray, k: np.ndarray, lo: np.ndarray,
    hi: np.ndarray, w: int,
) -> WindowBlock:
    """Windows of rows k, rows lo:hi each, padded to w rows (the last row repeated, weight 0).

    t (n,), z (m, n), sigma (n,) or (0,) for unit sigma.
    """
    position = lo + np.arange(w)[:, None]  # (w, b)
    padded = bool(np.any(hi - lo < w))
    rows = np.minimum(position, hi - 1) if padded else position
    weight = None
    if sigma.size == 0:
        variance_k = None
        if padded:
            weight = (position < hi).astype(np.float64)
    else:
        weight = np.where(position < hi, 1.0 / (sigma[rows] * sigma[rows]), 0.0)
        variance_k = sigma[k] * sigma[k]
    return WindowBlock(
        t=t[rows], z=z[:, rows], weight=weight, t_k=t[k], z_k=z[:, k], variance_k=variance_k,
    )


@dataclass
class _Plan:
    """How ``_differences`` computes p windows: slices where it can, gathered rows elsewhere.

    ``runs`` [(q0, q1, k0)]: outputs q0:q1 are the rows k0, k0 + 1, ... with windows of ``width``
    rows holding the tested point at position ``centre`` (served by slices); only the outputs
    where ``served`` (p,) is True keep that result. ``shared`` [(lo, centres)]: windows of
    ``width`` rows starting at the rows lo (b,), each tested at every position in ``centres``
    (the rows lo + c, output q = row): segment ends, whose rows share one window. ``gathered``
    (q, k, lo, hi): the other outputs q with MIN_SEGMENT_POINTS rows or more, row k predicted
    from rows lo:hi.
    """

    centre: int
    width: int
    runs: list[tuple[int, int, int]]
    served: np.ndarray
    gathered: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]
    shared: list[tuple[np.ndarray, range]] = field(default_factory=list)


def _covered(p: int, starts: np.ndarray, ends: np.ndarray) -> np.ndarray:
    """(p,) bool, True inside the sorted, disjoint ranges starts[i]:ends[i]."""
    lengths = np.diff(np.r_[0, np.c_[starts, ends].ravel(), p])  # gap, range, gap, ..., gap
    return np.repeat(np.tile([False, True], starts.size + 1)[: lengths.size], lengths)


def _plan_windows(targets: np.ndarray, lo: np.ndarray, hi: np.ndarray, n: int) -> _Plan:
    """The plan for arbitrary windows: slices serve the commonest shape in consecutive rows.

    Most windows are [k - n1, k + n2] (segment ends and short segments are the exceptions), so
    the commonest (position of k, size) is computed for every row of each run of _MIN_RUN or
    more consecutive targets, the exceptions included, and kept only where it is right.
    """
    size, position = hi - lo, targets - lo
    w = int(size.max(initial=0))
    if w < MIN_SEGMENT_POINTS:
        empty = np.zeros(0, np.int64)
        return _Plan(0, 0, [], np.zeros(targets.size, bool), (empty, empty, empty, empty))
    full = size == w
    c = int(np.bincount(position[full]).argmax())
    inside = (targets >= c) & (targets - c + w <= n)
    cut = np.flatnonzero((np.diff(targets) != 1) | (inside[1:] != inside[:-1])) + 1
    starts, ends = np.r_[0, cut], np.r_[cut, targets.size]
    keep = inside[starts] & (ends - starts >= _MIN_RUN)
    runs = [(a, b, int(targets[a])) for a, b in zip(starts[keep], ends[keep], strict=True)]
    served = _covered(targets.size, starts[keep], ends[keep]) & full & (position == c)
    q = np.flatnonzero(~served & (size >= MIN_SEGMENT_POINTS))
    return _Plan(c, w, runs, served, (q, targets[q], lo[q], hi[q]))


def _plan_segments(starts: np.ndarray, ends: np.ndarray, n1: int, n2: int) -> _Plan:
    """The plan for every row of contiguous segments (rows starts[i]:ends[i], covering 0:n).

    The interior rows of segments of n1 + n2 + 1 rows or more have the window [k - n1, k + n2]
    and are sliced; their first n1 rows share the window of the segment's first n1 + n2 + 1
    rows, their last n2 rows that of its last ones; the rows of shorter segments (the whole
    segment) are gathered: the rule of ``window_bounds``.
    """
    n = int(ends[-1]) if ends.size else 0
    w = n1 + n2 + 1
    length = ends - starts
    long = length >= w
    served = _covered(n, starts[long] + n1, ends[long] - n2)
    # One run from the first interior row to the last: the rows between segments are computed
    # with the wrong window and dropped (served is False there), which is cheaper than cutting.
    first, stop = (int(starts[long][0]) + n1, int(ends[long][-1]) - n2) if long.any() else (0, 0)
    runs = [(first, stop, first)] if stop > first else []
    shared = [(starts[long], range(n1)), (ends[long] - w, range(w - n2, w))]
    medium = (length >= MIN_SEGMENT_POINTS) & ~long
    m_len = length[medium]
    lo, hi = np.repeat(starts[medium], m_len), np.repeat(ends[medium], m_len)
    k = lo + np.arange(lo.size) - np.repeat(np.cumsum(m_len) - m_len, m_len)
    return _Plan(n1, w, runs, served, (k, k, lo, hi), shared)


def worker_threads() -> int:
    """Threads for the numpy kernels: NUMBA_NUM_THREADS when set (the knob of the numba
    detectors), else the CPUs this process may run on."""
    env = os.environ.get("NUMBA_NUM_THREADS", "")
    if env.isdigit() and int(env) > 0:
        return int(env)
    affinity = getattr(os, "sched_getaffinity", None)
    return len(affinity(0)) if affinity else (os.cpu_count() or 1)


def _differences(
    t: np.ndarray, z: np.ndarray, sigma: np.ndarray, plan: _Plan, p: int
) -> tuple[np.ndarray, np.ndarray]:
    """Run a plan: dz (p, m) and sigma_dz (p,) as ``window_differences`` returns them.

    t (n,), z (m, n) C-contiguous, sigma (n,) or (0,). Blocks of _BLOCK windows run on
    ``worker_threads()`` threads (numpy releases the GIL inside its loops).
    """
    dz = np.full((z.shape[0], p), np.nan)  # (m, p) while filled: blocks write rows
    sigma_dz = np.full(p, np.nan)

    def sliced(q0: int, q1: int, k0: int) -> None:
        block = _sliced_block(t, z, sigma, k0, k0 + q1 - q0, plan.centre, plan.width)
        d, s = _block_differences(block)
        keep = plan.served[q0:q1]  # the other rows belong to other tasks (other threads)
        np.copyto(dz[:, q0:q1], d, where=keep)
        np.copyto(sigma_dz[q0:q1], s, where=keep)

    q, k, lo, hi = plan.gathered
    width = int(np.max(hi - lo, initial=0))
    full = np.flatnonzero(hi - lo == width)  # full windows first: their blocks need no padding
    q, k, lo, hi = (np.r_[a[full], np.delete(a, full)] for a in (q, k, lo, hi))

    def gathered(a: int, b: int) -> None:
        block = _gathered_block(t, z, sigma, k[a:b], lo[a:b], hi[a:b], width)
        dz[:, q[a:b]], sigma_dz[q[a:b]] = _block_differences(block)

    def shared(window_lo: np.ndarray, centres: range) -> None:
        whole = _gathered_block(t, z, sigma, window_lo, window_lo, window_lo + plan.width,
                                plan.width)  # gathered once, tested at every centre
        for c in centres:
            row = window_lo + c
            variance_k = None if whole.variance_k is None else sigma[row] * sigma[row]
            block = replace(whole, t_k=whole.t[c], z_k=whole.z[:, c], variance_k=variance_k)
            dz[:, row], sigma_dz[row] = _block_differences(block)

    # About _BLOCK windows per task; the shared ones (a window per centre) first, so that the
    # threads do not end on one long task.
    tasks: list[tuple[Callable[..., None], tuple]] = [
        (shared, (window_lo[a : a + per_task], centres))
        for window_lo, centres in plan.shared
        for per_task in [max(1, _BLOCK // max(len(centres), 1))]
        for a in range(0, window_lo.size, per_task)
    ]
    tasks += [
        (sliced, (a, min(q1, a + _BLOCK), k0 + a - q0))
        for q0, q1, k0 in plan.runs
        for a in range(q0, q1, _BLOCK)
    ]
    tasks += [(gathered, (a, min(q.size, a + _BLOCK))) for a in range(0, q.size, _BLOCK)]
    threads = min(worker_threads(), len(tasks))
    if p < _PARALLEL_POINTS or threads < 2:
        for fn, args in tasks:
            fn(*args)
    else:
        with ThreadPoolExecutor(threads) as pool:
            for _ in pool.map(lambda task: task[0](*task[1]), tasks):
                pass
    return dz.T, sigma_dz


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
    a_0(k) = 1). Eq. 17 is dz / sigma_dz[:, None]. Every point is computed alone, with the
    same operations in the same order whether its window is sliced or gathered, so the result
    does not depend on how the points are split into calls, blocks or threads.
    """
    t = np.ascontiguousarray(t, dtype=np.float64)
    z_rows = np.ascontiguousarray(np.asarray(z, dtype=np.float64).T)  # (m, n): rows slice fast
    sigma = np.ascontiguousarray(sigma, dtype=np.float64)
    targets = np.asarray(targets, dtype=np.int64)
    plan = _plan_windows(targets, np.asarray(lo, np.int64), np.asarray(hi, np.int64), t.size)
    return _differences(t, z_rows, sigma, plan, targets.size)


def segment_differences(
    t: np.ndarray, z: np.ndarray, starts: np.ndarray, ends: np.ndarray, n1: int, n2: int
) -> tuple[np.ndarray, np.ndarray]:
    """``window_differences`` with unit sigma for every row of the segments starts:ends.

    t (n,), z (m, n) C-contiguous (one row per series); the segments cover rows 0:n in order.
    Each row's window follows ``window_bounds``; equal to ``window_differences`` with those
    windows, without the (n,) window arrays.
    """
    plan = _plan_segments(starts, ends, n1, n2)
    return _differences(t, z, np.empty(0), plan, t.size)



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


def _median_positive_step(t: np.ndarray) -> float:
    """Median of the positive steps of a sorted time series; NaN if it has none."""
    dt = np.diff(t)
    dt = dt[dt > 0]
    if dt.size == 0:
        return math.nan
    middle = (dt.size - 1) // 2  # np.median's two middle values, without its NaN pass
    dt.partition([middle, dt.size // 2])
    return float((dt[middle] + dt[dt.size // 2]) / 2.0)


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
    """The declared checks (:class:`TemporalParameters`), then sigma and max_gap resolved."""
    p = TemporalParameters(n1=n1, n2=n2, sigma=sigma, alpha=alpha, max_gap=max_gap)
    sigma_arr = None if p.sigma == "auto" else np.broadcast_to(
        np.asarray(p.sigma, dtype=np.float64), (3,)).copy()
    gap = None if p.max_gap == "auto" else float(p.max_gap)
    return _Params(int(p.n1), int(p.n2), float(p.alpha), normal_critical_value(p.alpha),
                   sigma_arr, gap)


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


def _prepare(xyz: np.ndarray, t: np.ndarray, group: np.ndarray | None, p: _Params) -> _Sorted:
    """Drop points without a finite time or position, sort, resolve max_gap, cut segments."""
    valid = np.isfinite(t)
    for axis in range(3):
        valid &= np.isfinite(xyz[:, axis])
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
        value = p.max_gap if p.max_gap is not None else 5.0 * _median_positive_step(ts[start:end])
        gaps[g] = value if math.isfinite(value) else math.inf  # no positive step: one segment
        gap_by_group[gid] = value if math.isfinite(value) else None
    starts, ends = cut_segments(ts, g_bounds, gaps)
    return _Sorted(rows, ts, z, starts, ends, gap_by_group)


def _unit_differences(s: _Sorted, p: _Params) -> tuple[np.ndarray, np.ndarray]:
    """dz (m, 3) and sigma_dz (m,) of eqs. 15-16 with unit sigma; NaN where untested."""
    return segment_differences(s.t, s.z, s.starts, s.ends, p.n1, p.n2)


def estimate_sigma(dz_unit: np.ndarray, sigma_dz_unit: np.ndarray) -> tuple[np.ndarray, str]:
    """Robust per-axis sigma from unit-sigma prediction differences.

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
    dz, sdz = _unit_differences(s, p)
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
    ``warmup_points`` points (all of them if the stream is shorter), which are held back
    until then (with the rest of the chunk that completes them): sigma as in
    ``detect_temporal`` on those points, max_gap per group from that group's points among them
    (a group first seen later: from its first rows that hold a positive time step). The
    resolved values are in ``info``.
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
        head = slice(0, self._warmup_points)  # resolve from these; the chunk may hold more
        s = _prepare(xyz[head], t[head], None if group is None else group[head], self._p)
        if self._p.max_gap is None:
            self._gap_by_group.update(s.max_gap_by_group)
            for gid, gap in s.max_gap_by_group.items():
                if gap is not None:
                    self._tail(gid).max_gap = gap
        if self._sigma is None:
            dz, sdz = _unit_differences(s, self._p)
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
