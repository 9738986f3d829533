"""The temporal smoother compiled with numba: eqs. 11 and 14-16 one window at a time, all
windows on all cores, for unit sigma (the detector's case).

Each window runs the operations of the numpy blocks of :mod:`algorithms.temporal.smoother` in
the same order (sums in row order, no reassociation, no fused multiply-add), so the results
are the same to the last bit (tested); only the speed differs: about 27 ns a window on two
cores against about 100 ns. Compiled code needs numba's import and cached load, about 0.6 s in
a fresh process, so :func:`algorithms.temporal.windows.use_compiled` takes it for long series
or when numba is loaded anyway.
"""

from __future__ import annotations

import numpy as np

from algorithms.jit import njit, prange
from algorithms.temporal.smoother import _MIN_ONE_MINUS_A0, _SINGULAR_RATIO, MIN_SEGMENT_POINTS

#: Windows per parallel task, and windows computed side by side within a task (lanes: their
#: sums are independent chains the CPU can overlap, while each one keeps numpy's row order).
_BLOCK = 4096
_LANES = 32


@njit(cache=True, error_model="numpy", inline="always")
def _lanes(t, z, k, lo, w, count, out, dz, sigma_dz, q1, q2, v):
    """eqs. 11, 14-16 (unit sigma) for ``count`` windows of ``w`` rows side by side: row k[q]
    predicted from rows lo[q]:lo[q] + w, written to dz[:, out[q]] and sigma_dz[out[q]] when
    usable (left NaN otherwise). The operations of ``smoother_weights``,
    ``predict_from_window`` and ``difference_variance`` in their order. q1, q2 (>= w, lanes)
    and v (14, lanes): scratch."""
    t_k, inv_unit, alpha1, n1, cubes, gamma, beta1, n2, c1, c2, a_0 = (
        v[0], v[1], v[2], v[3], v[4], v[5], v[6], v[7], v[8], v[9], v[10])
    n0 = float(w)
    for q in range(count):
        t_k[q] = t[k[q]]
        inv_unit[q] = 1.0 / max(t_k[q] - t[lo[q]], t[lo[q] + w - 1] - t_k[q])
    for i in range(w):
        for q in range(count):
            q1[i, q] = (t[lo[q] + i] - t_k[q]) * inv_unit[q]
    for q in range(count):  # sums start from the first row, as numpy's _sum_rows
        alpha1[q] = q1[0, q]
    for i in range(1, w):
        for q in range(count):
            alpha1[q] += q1[i, q]
    for q in range(count):
        alpha1[q] /= n0
    for i in range(w):
        for q in range(count):
            q1[i, q] -= alpha1[q]
    for q in range(count):
        n1[q] = q1[0, q] * q1[0, q]
        cubes[q] = n1[q] * q1[0, q]
    for i in range(1, w):
        for q in range(count):
            square = q1[i, q] * q1[i, q]
            n1[q] += square
            cubes[q] += square * q1[i, q]
    for q in range(count):
        gamma[q], beta1[q] = cubes[q] / n1[q], n1[q] / n0
    for i in range(w):
        for q in range(count):
            q2[i, q] = (q1[i, q] - gamma[q]) * q1[i, q] - beta1[q]
    for q in range(count):
        n2[q] = q2[0, q] * q2[0, q]
    for i in range(1, w):
        for q in range(count):
            n2[q] += q2[i, q] * q2[i, q]
    for q in range(count):
        q1_k = -alpha1[q]
        q2_k = (q1_k - gamma[q]) * q1_k - beta1[q]
        c1[q], c2[q] = q1_k / n1[q], q2_k / n2[q]
        a_0[q] = 1.0 / n0 + c1[q] * q1_k + c2[q] * q2_k
    inv_n0 = 1.0 / n0
    for i in range(w):  # the weights a_i of eq. 11, in place of q_1
        for q in range(count):
            q1[i, q] = q1[i, q] * c1[q] + inv_n0 + q2[i, q] * c2[q]
    usable, z_k, prediction = v[11], v[12], v[13]
    for q in range(count):
        usable[q] = n2[q] > _SINGULAR_RATIO * n0 and 1.0 - a_0[q] > _MIN_ONE_MINUS_A0
    for j in range(z.shape[0]):  # eq. 15 relative to z(k): the terms start from the first row
        for q in range(count):
            z_k[q] = z[j, k[q]]
            prediction[q] = (z[j, lo[q]] - z_k[q]) * q1[0, q]
        for i in range(1, w):
            for q in range(count):
                prediction[q] += (z[j, lo[q] + i] - z_k[q]) * q1[i, q]
        for q in range(count):
            if usable[q]:
                dz[j, out[q]] = -(prediction[q] / (1.0 - a_0[q]))
    for q in range(count):
        if usable[q]:
            sigma_dz[out[q]] = np.sqrt(1.0 / (1.0 - a_0[q]))


@njit(cache=True, error_model="numpy", inline="always")
def _windows_of_block(t, z, k, lo, hi, out, count, dz, sigma_dz, width):
    """The windows k[:count] (rows lo:hi each) of one task, in lanes of equal width."""
    q1, q2 = np.empty((width, _LANES)), np.empty((width, _LANES))
    v = np.empty((14, _LANES))
    first = 0
    while first < count:
        w = hi[first] - lo[first]
        stop = first + 1
        while stop < count and stop - first < _LANES and hi[stop] - lo[stop] == w:
            stop += 1
        if w >= MIN_SEGMENT_POINTS:
            _lanes(t, z, k[first:stop], lo[first:stop], w, stop - first, out[first:stop], dz,
                   sigma_dz, q1, q2, v)
        first = stop


@njit(cache=True, error_model="numpy", parallel=True)
def window_differences_compiled(t, z, targets, lo, hi):
    """``windows.window_differences`` with unit sigma: dz (m, p), sigma_dz (p,) of the rows
    ``targets`` predicted from rows lo:hi each; t (n,), z (m, n) (any strides)."""
    p = targets.shape[0]
    dz = np.full((z.shape[0], p), np.nan)
    sigma_dz = np.full(p, np.nan)
    width = max(np.max(hi - lo), 1) if p else 1
    for b in prange((p + _BLOCK - 1) // _BLOCK):
        first, stop = b * _BLOCK, min(p, (b + 1) * _BLOCK)
        out = np.arange(first, stop)
        _windows_of_block(t, z, targets[first:stop], lo[first:stop], hi[first:stop], out,
                          stop - first, dz, sigma_dz, width)
    return dz, sigma_dz


@njit(cache=True, error_model="numpy", parallel=True)
def segment_differences_compiled(t, z, starts, ends, n1, n2):
    """``windows.segment_differences``: dz (m, n), sigma_dz (n,) for every row of the segments
    starts:ends (covering 0:n), each row's window by the rule of ``windows.window_bounds``."""
    n = t.shape[0]
    size = n1 + n2 + 1
    dz = np.full((z.shape[0], n), np.nan)
    sigma_dz = np.full(n, np.nan)
    for b in prange((n + _BLOCK - 1) // _BLOCK):
        first, stop = b * _BLOCK, min(n, (b + 1) * _BLOCK)
        rows = np.arange(first, stop)
        lo, hi = np.empty_like(rows), np.empty_like(rows)
        s = np.searchsorted(starts, first, side="right") - 1
        for q in range(stop - first):
            k = first + q
            while k >= ends[s]:
                s += 1
            start, end = starts[s], ends[s]
            if end - start < size:
                lo[q], hi[q] = start, end
            else:
                lo[q] = min(max(k - n1, start), end - size)
                hi[q] = lo[q] + size
        _windows_of_block(t, z, rows, lo, hi, rows, stop - first, dz, sigma_dz, size)
    return dz, sigma_dz


def load() -> None:
    """Run each kernel once on a few windows, with the array types the detectors pass, so that
    numba's cached code is loaded (compiled, the first time) before a long series needs it."""
    t = np.arange(16.0)
    xyz = np.zeros((16, 3))  # the stream's (n, 3) rows, passed transposed
    rows = np.arange(5, 11)
    window_differences_compiled(t, xyz.T, rows, rows - 5, rows + 6)
    segment_differences_compiled(t, np.zeros((3, 16)), np.array([0]), np.array([16]), 5, 5)
