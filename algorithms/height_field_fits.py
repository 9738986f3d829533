"""The numba kernels of the ``height_field`` detector (:mod:`algorithms.height_field`).

Per point: the principal-axis frame of its neighbours (step 1 of the detector), the explicit
height field w = a + b u + c v fitted by least squares with the tested point's residual,
leverage and the fit's residual standard error (step 2), on the full patch and the four half
patches (step 3); then each fit's term and the point's score (steps 4 and 5). Parallel over
points. Kept out of the detector module, so that importing the detector (for its
parameters) does not import numba.
"""

from __future__ import annotations

import numpy as np

from algorithms.jit import njit, prange

#: Fewest neighbours a half patch needs to be fitted (3 parameters + 3 degrees of freedom).
MIN_HALF_POINTS = 6


@njit(cache=True)
def frame_of(xyz: np.ndarray, idx: np.ndarray, cnt: int) -> tuple[np.ndarray, np.ndarray]:
    """Centroid (3,) and principal axes (3, 3) of the points xyz[idx[:cnt]].

    Columns of the axes matrix are eigenvectors of the scatter matrix in ascending eigenvalue
    order: column 0 is the normal w, columns 1 and 2 span the tangent plane (v, u).
    """
    c = np.zeros(3)
    for j in range(cnt):
        for a in range(3):
            c[a] += xyz[idx[j], a]
    c /= cnt
    s = np.zeros((3, 3))
    for j in range(cnt):
        for a in range(3):
            da = xyz[idx[j], a] - c[a]
            for b in range(3):
                s[a, b] += da * (xyz[idx[j], b] - c[b])
    _, vec = np.linalg.eigh(s)
    return c, vec


@njit(cache=True)
def height_field_fit(uvw: np.ndarray, sel: np.ndarray, cnt: int, up: float, vp: float,
                     wp: float) -> tuple[float, float, float]:
    """Least-squares w = a + b u + c v on the rows uvw[sel[:cnt]], tested at (up, vp, wp).

    Returns (residual wp - w(up, vp), leverage h = x_p^T (X^T X)^-1 x_p, residual standard
    error sqrt(RSS / (cnt - 3))). NaN residual when X^T X is singular (collinear points).
    """
    m = np.zeros((3, 3))
    rhs = np.zeros(3)
    ww = 0.0
    for j in range(cnt):
        r = sel[j]
        x0, x1, x2, w = 1.0, uvw[r, 0], uvw[r, 1], uvw[r, 2]
        m[0, 0] += 1.0
        m[0, 1] += x1
        m[0, 2] += x2
        m[1, 1] += x1 * x1
        m[1, 2] += x1 * x2
        m[2, 2] += x2 * x2
        rhs[0] += x0 * w
        rhs[1] += x1 * w
        rhs[2] += x2 * w
        ww += w * w
    m[1, 0] = m[0, 1]
    m[2, 0] = m[0, 2]
    m[2, 1] = m[1, 2]
    # cofactor inverse of the symmetric 3 x 3 normal matrix
    c00 = m[1, 1] * m[2, 2] - m[1, 2] * m[1, 2]
    c01 = m[0, 2] * m[1, 2] - m[0, 1] * m[2, 2]
    c02 = m[0, 1] * m[1, 2] - m[0, 2] * m[1, 1]
    det = m[0, 0] * c00 + m[0, 1] * c01 + m[0, 2] * c02
    scale = m[0, 0] * m[1, 1] * m[2, 2]
    if not det > 1e-12 * scale:
        return np.nan, np.nan, np.nan
    inv = np.empty((3, 3))
    inv[0, 0] = c00
    inv[0, 1] = c01
    inv[0, 2] = c02
    inv[1, 1] = m[0, 0] * m[2, 2] - m[0, 2] * m[0, 2]
    inv[1, 2] = m[0, 1] * m[0, 2] - m[0, 0] * m[1, 2]
    inv[2, 2] = m[0, 0] * m[1, 1] - m[0, 1] * m[0, 1]
    inv[1, 0] = inv[0, 1]
    inv[2, 0] = inv[0, 2]
    inv[2, 1] = inv[1, 2]
    inv /= det
    beta = inv @ rhs
    xp = np.array([1.0, up, vp])
    lev = xp @ inv @ xp
    rss = ww - beta @ rhs  # RSS = w^T w - beta^T X^T w for the least-squares beta
    dof = cnt - 3
    rms = np.sqrt(max(rss, 0.0) / dof) if dof > 0 else np.nan
    return wp - (beta[0] + beta[1] * up + beta[2] * vp), lev, rms


@njit(cache=True)
def point_terms(xyz: np.ndarray, nbr_row: np.ndarray, i: int, out: np.ndarray,
                halves: bool = True) -> int:
    """Fits of point i on its neighbours nbr_row (i and entries < 0 skipped): full + 4 halves
    (the full patch alone without ``halves``).

    out (5, 4) receives per fit (residual along the upward normal w, leverage, rms, w's z
    component), NaN where a half patch holds fewer than MIN_HALF_POINTS points (or is not
    fitted). Returns the number of neighbours used.
    """
    k = nbr_row.size
    idx = np.empty(k, np.int64)
    cnt = 0
    for j in range(k):
        if nbr_row[j] != i and nbr_row[j] >= 0:
            idx[cnt] = nbr_row[j]
            cnt += 1
    out[:] = np.nan
    if cnt < MIN_HALF_POINTS:
        return cnt
    c, vec = frame_of(xyz, idx, cnt)
    if vec[2, 0] < 0.0:  # orient the normal w upwards (towards a mobile scanner's side)
        for b in range(3):
            vec[b, 0] = -vec[b, 0]
    uvw = np.empty((cnt, 3))
    for j in range(cnt):
        for a in range(3):
            uvw[j, a] = 0.0
        for b in range(3):
            d = xyz[idx[j], b] - c[b]
            uvw[j, 0] += d * vec[b, 2]
            uvw[j, 1] += d * vec[b, 1]
            uvw[j, 2] += d * vec[b, 0]
    pu = 0.0
    pv = 0.0
    pw = 0.0
    for b in range(3):
        d = xyz[i, b] - c[b]
        pu += d * vec[b, 2]
        pv += d * vec[b, 1]
        pw += d * vec[b, 0]
    sel = np.arange(cnt)
    r, h, s = height_field_fit(uvw, sel, cnt, pu, pv, pw)
    out[0, 0] = r
    out[0, 1] = h
    out[0, 2] = s
    out[:, 3] = vec[2, 0]
    half = np.empty(cnt, np.int64)
    for f in range(4 if halves else 0):
        axis = f // 2
        sign = 1.0 if f % 2 == 0 else -1.0
        p_coord = pu if axis == 0 else pv
        m = 0
        for j in range(cnt):
            if sign * (uvw[j, axis] - p_coord) > 0.0:
                half[m] = j
                m += 1
        if m >= MIN_HALF_POINTS:
            r, h, s = height_field_fit(uvw, half, m, pu, pv, pw)
            out[f + 1, 0] = r
            out[f + 1, 1] = h
            out[f + 1, 2] = s
    return cnt


@njit(cache=True, parallel=True)
def terms_of(xyz: np.ndarray, nbr: np.ndarray, points: np.ndarray,
             halves: bool = True) -> np.ndarray:
    """point_terms of each of ``points`` (m,) on its row of nbr (m, k): (m, 5, 4) residual,
    leverage, rms, normal z (the full patch's alone without ``halves``)."""
    m = nbr.shape[0]
    terms = np.full((m, 5, 4), np.nan)
    for r in prange(m):
        point_terms(xyz, nbr[r], points[r], terms[r], halves)
    return terms


def all_terms(xyz: np.ndarray, nbr: np.ndarray) -> np.ndarray:
    """:func:`terms_of` every point, row i of nbr (n, k) being point i's neighbours."""
    return terms_of(xyz, nbr, np.arange(nbr.shape[0], dtype=np.int64))


@njit(cache=True)
def _fit_term(terms_f: np.ndarray, sigma: float, rms_weight: float, one_sided_nz: float,
              max_leverage: float) -> float:
    """One fit's term max(|r| / (sigma sqrt(1 + h)), rms_weight rms / sigma); NaN if unusable.

    A fit is unusable when singular or when p lies so far outside its points (leverage above
    max_leverage: nearly collinear neighbours along one scan line) that it cannot vouch for p.
    On ground-like fits (upward normal z >= one_sided_nz) a residual below the surface is 0.
    """
    r = terms_f[0]
    if np.isnan(r) or terms_f[1] > max_leverage:
        return np.nan
    if r < 0.0 and terms_f[3] >= one_sided_nz:
        r = 0.0
    t = abs(r) / (sigma * np.sqrt(1.0 + terms_f[1]))
    g = rms_weight * terms_f[2] / sigma
    return g if g > t else t


@njit(cache=True, parallel=True)
def scores_from_terms(terms: np.ndarray, sigma: float, rms_weight: float, one_sided_nz: float,
                      half_gate: float, max_leverage: float) -> np.ndarray:
    """Score (n,): the full patch's term, or the smallest term over the full and half patches
    where the full patch is not one surface (its rms above half_gate sigma: an edge, a step).

    Early returns (droplets, dust, multi-path) lie in front of a surface, i.e. above the ground
    for a scanner on a vehicle roof, hence the one-sided rule of ``_fit_term``. NaN where no
    fit is usable.
    """
    n = terms.shape[0]
    score = np.full(n, np.nan)
    for i in prange(n):
        best = _fit_term(terms[i, 0], sigma, rms_weight, one_sided_nz, max_leverage)
        if not terms[i, 0, 2] <= half_gate * sigma:  # also when the full fit is unusable
            for f in range(1, terms.shape[1]):
                t = _fit_term(terms[i, f], sigma, rms_weight, one_sided_nz, max_leverage)
                if t < best or np.isnan(best):
                    best = t
        score[i] = best
    return score


@njit(cache=True, parallel=True)
def seen_again(xyz: np.ndarray, t: np.ndarray, nbr: np.ndarray, points: np.ndarray,
               radius: float, min_dt: float) -> np.ndarray:
    """(m,) bool: one of point ``points[r]``'s neighbours ``nbr[r]`` lies within ``radius`` and
    was recorded at least ``min_dt`` seconds before or after it (NaN times never count)."""
    m = nbr.shape[0]
    out = np.zeros(m, dtype=np.bool_)
    r2 = radius * radius
    for r in prange(m):
        p = points[r]
        for c in range(nbr.shape[1]):
            j = nbr[r, c]
            if abs(t[j] - t[p]) >= min_dt:
                d2 = 0.0
                for a in range(3):
                    e = xyz[j, a] - xyz[p, a]
                    d2 += e * e
                if d2 <= r2:
                    out[r] = True
                    break
    return out
