"""Windows of the temporal detector: the rows that predict each point, and many windows at once.

``window_bounds`` gives each point's window, [k - n1, k + n2] shifted inside its segment (the
paper's "window size adjusted at the start and end of each line"). ``window_differences`` (any
windows) and ``segment_differences`` (every row of cut segments) evaluate eqs. 14-16
(:mod:`algorithms.temporal.smoother`) for many points: a plan serves the commonest window shape
of consecutive rows by slices (views, no copy) and gathers the rows of the other windows, and
blocks of windows run on ``worker_threads()`` threads (numpy releases the GIL inside its loops).
Every point is computed alone, with the same operations whichever way its window is served.
Long series take the compiled smoother instead (``use_compiled``), which gives the same bits.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace

import numpy as np

from algorithms.temporal.smoother import MIN_SEGMENT_POINTS, WindowBlock, block_differences
from algorithms.threads import worker_threads

#: Windows per block (a block's temporaries of this length stay near the CPU), and the number
#: of windows below which ``_differences`` runs on one thread.
_BLOCK = 16384
_PARALLEL_POINTS = 2 * _BLOCK

#: Shortest run of alike consecutive windows that ``window_differences`` serves by slices.
_MIN_RUN = 64

#: Windows from which the compiled smoother (:mod:`algorithms.temporal.compiled`) repays
#: numba's import and cached load, about 0.6 s in a fresh process. Measured on the temporal
#: command: at 4 M points both kernels take as long, at 12 M the compiled one 10-15 % less.
COMPILED_MIN_WINDOWS = 4_000_000


def use_compiled(windows: int, given: bool | None = None) -> bool:
    """Whether to run the compiled smoother for ``windows`` windows: as ``given`` when the
    caller chose, else when they are enough to repay numba's import, or numba is loaded
    already. Both give the same bits."""
    if given is not None:
        return given
    return windows >= COMPILED_MIN_WINDOWS or "numba" in sys.modules


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
        d, s = block_differences(block)
        keep = plan.served[q0:q1]  # the other rows belong to other tasks (other threads)
        np.copyto(dz[:, q0:q1], d, where=keep)
        np.copyto(sigma_dz[q0:q1], s, where=keep)

    q, k, lo, hi = plan.gathered
    width = int(np.max(hi - lo, initial=0))
    full = np.flatnonzero(hi - lo == width)  # full windows first: their blocks need no padding
    q, k, lo, hi = (np.r_[a[full], np.delete(a, full)] for a in (q, k, lo, hi))

    def gathered(a: int, b: int) -> None:
        block = _gathered_block(t, z, sigma, k[a:b], lo[a:b], hi[a:b], width)
        dz[:, q[a:b]], sigma_dz[q[a:b]] = block_differences(block)

    def shared(window_lo: np.ndarray, centres: range) -> None:
        whole = _gathered_block(t, z, sigma, window_lo, window_lo, window_lo + plan.width,
                                plan.width)  # gathered once, tested at every centre
        for c in centres:
            row = window_lo + c
            variance_k = None if whole.variance_k is None else sigma[row] * sigma[row]
            block = replace(whole, t_k=whole.t[c], z_k=whole.z[:, c], variance_k=variance_k)
            dz[:, row], sigma_dz[row] = block_differences(block)

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
    *,
    compiled: bool | None = None,
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

    compiled : run the compiled smoother (unit sigma only; the same bits), None: ``use_compiled``.
    """
    t = np.ascontiguousarray(t, dtype=np.float64)
    sigma = np.ascontiguousarray(sigma, dtype=np.float64)
    targets = np.asarray(targets, dtype=np.int64)
    if sigma.size == 0 and use_compiled(targets.size, compiled):
        from algorithms.temporal.compiled import window_differences_compiled

        z_rows = np.asarray(z, dtype=np.float64).T  # a view: the kernel takes any strides
        dz, sigma_dz = window_differences_compiled(t, z_rows, targets, np.asarray(lo, np.int64),
                                                   np.asarray(hi, np.int64))
        return dz.T, sigma_dz
    z_rows = np.ascontiguousarray(np.asarray(z, dtype=np.float64).T)  # (m, n): rows slice fast
    plan = _plan_windows(targets, np.asarray(lo, np.int64), np.asarray(hi, np.int64), t.size)
    return _differences(t, z_rows, sigma, plan, targets.size)


def segment_differences(
    t: np.ndarray, z: np.ndarray, starts: np.ndarray, ends: np.ndarray, n1: int, n2: int,
    *, compiled: bool | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """``window_differences`` with unit sigma for every row of the segments starts:ends.

    t (n,), z (m, n) C-contiguous (one row per series); the segments cover rows 0:n in order.
    Each row's window follows ``window_bounds``; equal to ``window_differences`` with those
    windows, without the (n,) window arrays. ``compiled`` as in ``window_differences``.
    """
    if use_compiled(t.size, compiled):
        from algorithms.temporal.compiled import segment_differences_compiled

        dz, sigma_dz = segment_differences_compiled(
            t, z, np.asarray(starts, np.int64), np.asarray(ends, np.int64), n1, n2)
        return dz.T, sigma_dz
    plan = _plan_segments(starts, ends, n1, n2)
    return _differences(t, z, np.empty(0), plan, t.size)
