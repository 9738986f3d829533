"""The ``height_field`` detector: leave-one-out local height fields with edge-aware half patches.

A robust successor of the paper's algorithm (b) (eqs. 18-31) for mobile-mapping clouds.
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

A point is flagged when its score exceeds ``threshold``. The kernels (numba, parallel over points)
are in :mod:`algorithms.height_field_fits`; the neighbour search is scipy's cKDTree. Both are
imported when the detector runs, not with its parameters.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Literal

import numpy as np

from algorithms.checks import check_xyz
from algorithms.params import Parameters, param
from algorithms.result import DetectorResult
from algorithms.stats import MAD_TO_SIGMA

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


def studentised_full(terms: np.ndarray) -> np.ndarray:
    """(n,) full-patch studentised residual r / sqrt(1 + h) in metres (NaN where untested)."""
    return terms[:, 0, 0] / np.sqrt(1.0 + terms[:, 0, 1])


def estimate_sigma(terms: np.ndarray) -> float:
    """Robust sigma (m): MAD of the full-patch studentised residuals (evenly strided sample)."""
    return sigma_of_residuals([studentised_full(terms)])


def sigma_of_residuals(parts: Iterable[np.ndarray], sample: int = SIGMA_SAMPLE) -> float:
    """:func:`estimate_sigma` of the residuals of all the points, given in order as ``parts``
    (NaN: untested), reading each part twice and keeping only the sample: the MAD of every
    ``max(1, finite // sample)``-th finite residual. ``parts`` is called on twice (a list, or
    memory-mapped pieces of a large array)."""
    parts = list(parts)
    finite = sum(int(np.count_nonzero(np.isfinite(p))) for p in parts)
    if finite == 0:
        return float("nan")
    step = max(1, finite // sample)
    kept, offset = [], 0
    for part in parts:
        r = np.asarray(part)[np.isfinite(part)]
        kept.append(r[(-offset) % step::step])
        offset += r.size
    r = np.concatenate(kept)
    return float(MAD_TO_SIGMA * np.median(np.abs(r - np.median(r))))


def full_residuals(xyz: np.ndarray, k: int) -> np.ndarray:
    """(n,) full-patch studentised residual of each point (NaN where untested), as
    ``sigma="auto"`` estimates from them (the points centred as :func:`detect_height_field`
    centres them)."""
    from algorithms.height_field_fits import all_terms

    arr = check_xyz(xyz)
    if len(arr) == 0:
        return np.zeros(0)
    local = arr - arr.mean(axis=0)
    return studentised_full(all_terms(local, neighbours(local, k)))


def neighbours(xyz: np.ndarray, k: int) -> np.ndarray:
    """(n, k + 1) indices of each point's k + 1 nearest points (itself normally first)."""
    from scipy.spatial import cKDTree

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
    from algorithms.height_field_fits import all_terms, scores_from_terms

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
