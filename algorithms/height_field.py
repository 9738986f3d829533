"""The ``height_field`` detector: leave-one-out local height fields with edge-aware half patches.

A robust successor of the paper's algorithm (b) (eqs. 18-31) for mobile-mapping clouds (issue 5).
The paper's T_i (eq. 31) is limited by two facts its authors name: the tested point takes part in
fitting the surface it is tested against, and rough objects (curbs, manholes, car edges) raise
false alarms because one smooth surface cannot follow an edge. Here, for every point p:

1. its k nearest neighbours (p itself excluded: leave-one-out) define a principal-axis frame
   (u, v in the tangent plane, w along the normal: the eigenvectors of their scatter matrix);
2. an explicit height field w = a + b u + c v (the first-order case of the paper's explicit
   surface, eq. 18 solved for w; on a few centimetres a plane) is fitted by least squares to
   the neighbours, and p's externally studentised residual is
   ``r / (sigma * sqrt(1 + x_p^T (X^T X)^-1 x_p))`` with x_p = (1, u_p, v_p): the exact
   standard deviation of a new observation's deviation from a least-squares prediction;
3. where the full patch is not one surface (its residual standard error above ``HALF_GATE``
   sigmas: an edge, a step), the same fit is repeated on the four half patches u > 0, u < 0,
   v > 0, v < 0 (each with at least ``MIN_HALF_POINTS`` neighbours): a point on a curb, a raised
   manhole lid or a car's edge lies on the surface of at least one side, an outlier on none;
   a fit whose leverage exceeds ``MAX_LEVERAGE`` (p far outside nearly collinear neighbours)
   cannot vouch for p;
4. a fit only vouches for p as far as it is itself a surface: each fit's term is
   ``max(|studentised residual|, rms_weight * rms / sigma)``, with ``rms`` its own residual
   standard error, so a "surface" made of scattered droplets cannot explain its members;
   on ground-like fits (upward normal within ~45 degrees of vertical, ``one_sided``) only
   residuals above the surface count: early returns lie between the scanner and the ground;
5. the score is the smallest term over the usable fits, in units of one ``sigma`` for the whole
   cloud (``"auto"``: the MAD of all full-patch studentised residuals, so no error is guessed).

A point is flagged when its score exceeds ``threshold``. The kernel is numba, parallel over points;
the neighbour search is scipy's cKDTree.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy.spatial import cKDTree

from algorithms.checks import check_xyz
from algorithms.jit import njit, prange
from algorithms.params import Parameters, param
from algorithms.result import DetectorResult
from algorithms.stats import MAD_TO_SIGMA

#: Fewest neighbours a half patch needs to be fitted (3 parameters + 3 degrees of freedom).
MIN_HALF_POINTS = 6

#: Upward-normal z above which a fit is ground-like for the one-sided test (45 degrees).
ONE_SIDED_NZ = 0.7

#: Leverage x_p^T (X^T X)^-1 x_p above which a fit cannot vouch for p (extrapolation far
#: outside its points, e.g. neighbours all on one scan line).
MAX_LEVERAGE = 10.0

#: A full patch whose residual standard error is at most this many sigmas is one surface: its
#: half patches are not consulted (they would only add extrapolation noise).
HALF_GATE = 2.0

#: Points per kNN batch (memory: batch x k x 8 bytes of indices).
KNN_BATCH = 262_144

#: Points whose full-patch residuals are used to estimate sigma when ``sigma="auto"``.
SIGMA_SAMPLE = 200_000


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
def point_terms(xyz: np.ndarray, nbr_row: np.ndarray, i: int, out: np.ndarray) -> int:
    """Fits of point i on its neighbours nbr_row (i and entries < 0 skipped): full + 4 halves.

    out (5, 4) receives per fit (residual along the upward normal w, leverage, rms, w's z
    component), NaN where a half patch holds fewer than MIN_HALF_POINTS points. Returns the
    number of neighbours used.
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
    for f in range(4):
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
def all_terms(xyz: np.ndarray, nbr: np.ndarray) -> np.ndarray:
    """point_terms for every row of nbr (n, k): (n, 5, 4) residual, leverage, rms, normal z."""
    n = nbr.shape[0]
    terms = np.full((n, 5, 4), np.nan)
    for i in prange(n):
        point_terms(xyz, nbr[i], i, terms[i])
    return terms


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


def studentised_full(terms: np.ndarray) -> np.ndarray:
    """(n,) full-patch studentised residual r / sqrt(1 + h) in metres (NaN where untested)."""
    return terms[:, 0, 0] / np.sqrt(1.0 + terms[:, 0, 1])


def estimate_sigma(terms: np.ndarray) -> float:
    """Robust sigma (m): MAD of the full-patch studentised residuals (evenly strided sample)."""
    r = studentised_full(terms)
    r = r[np.isfinite(r)]
    if r.size == 0:
        return float("nan")
    step = max(1, r.size // SIGMA_SAMPLE)
    r = r[::step]
    return float(MAD_TO_SIGMA * np.median(np.abs(r - np.median(r))))


def neighbours(xyz: np.ndarray, k: int) -> np.ndarray:
    """(n, k + 1) indices of each point's k + 1 nearest points (itself normally first)."""
    tree = cKDTree(xyz)
    n = len(xyz)
    kk = min(k + 1, n)
    out = np.empty((n, kk), dtype=np.int64)
    for s in range(0, n, KNN_BATCH):
        _, idx = tree.query(xyz[s:s + KNN_BATCH], k=kk, workers=-1)
        out[s:s + KNN_BATCH] = idx.reshape(-1, kk)
    return out


@dataclass(frozen=True)
class HeightFieldParameters(Parameters):
    """Mobile mapping: leave-one-out height fields on k neighbours and four half patches."""

    k: int = param(24, "Neighbours per patch, the point excluded.", ge=8, le=200)
    sigma: float | Literal["auto"] = param(
        "auto", "Coordinate standard deviation in metres (> 0), or 'auto' for the MAD of the "
        "cloud's full-patch studentised residuals (reported in the statistics).", gt=0)
    threshold: float = param(
        9.0, "Score (in sigmas) above which a point is flagged.", gt=0, le=1000)
    rms_weight: float = param(
        0.5, "Weight of a fit's own residual standard error: a patch of scattered points "
        "cannot vouch for its members.", ge=0, le=100)
    one_sided: bool = param(
        True, "On ground-like patches (normal within 45 degrees of vertical) count only points "
        "above the surface (early returns).")


def detect_height_field(
    xyz: np.ndarray,
    *,
    k: int = 24,
    sigma: float | str = "auto",
    threshold: float = 9.0,
    rms_weight: float = 0.5,
    one_sided: bool = True,
) -> DetectorResult:
    """Edge-aware leave-one-out height-field outlier test (see the module docstring).

    Parameters
    ----------
    xyz : (n, 3) float64 coordinates in metres (centred internally: coordinates near 5e6 m keep
        their precision).
    k : neighbours per patch, the tested point excluded.
    sigma : metres, or "auto" (robust estimate from the cloud, reported in ``info``).
    threshold : score in units of sigma above which a point is flagged.
    rms_weight : weight of a fit's own residual standard error in its term (0: residual only).
    one_sided : on ground-like fits count only residuals above the surface.

    Returns
    -------
    DetectorResult with score (n,) (NaN where fewer than MIN_HALF_POINTS neighbours exist or every
    fit is singular), flagged = score > threshold, critical_value = threshold.
    """
    HeightFieldParameters(k=k, sigma=sigma, threshold=threshold, rms_weight=rms_weight,
                          one_sided=one_sided)
    arr = check_xyz(xyz)
    n = len(arr)
    info: dict = {"k": int(k), "threshold": float(threshold), "rms_weight": float(rms_weight),
                  "one_sided": bool(one_sided), "points": int(n)}
    if n == 0:
        info.update(sigma=None, sigma_source="none", points_tested=0, points_flagged=0)
        return DetectorResult(np.zeros(0), np.zeros(0, bool), float(threshold), info)
    local = arr - arr.mean(axis=0)
    terms = all_terms(local, neighbours(local, k))
    if sigma == "auto":
        sig, source = estimate_sigma(terms), "auto"
    else:
        sig, source = float(sigma), "given"
    if not sig > 0:  # a perfect synthetic surface: every residual is rounding
        sig = float(np.finfo(float).eps * max(1.0, float(np.abs(local).max())))
    score = scores_from_terms(terms, sig, float(rms_weight), ONE_SIDED_NZ if one_sided else 2.0,
                              HALF_GATE, MAX_LEVERAGE)
    flagged = score > threshold
    info.update(
        sigma=sig, sigma_source=source,
        points_tested=int(np.count_nonzero(~np.isnan(score))),
        points_flagged=int(np.count_nonzero(flagged)),
    )
    return DetectorResult(score=score, flagged=flagged, critical_value=float(threshold), info=info)
