"""The numba kernels of the ``section`` detector (:mod:`algorithms.section`): the fit-and-remove
loop of one section (eqs. 18-31 by :func:`algorithms.quadric.fit_masked`, refitted until no
outlier remains) and all sections in parallel. Kept out of the detector module, so that
importing the detector (for its parameters) does not import numba.
"""

from __future__ import annotations

import numpy as np

from algorithms.fit_outcome import CONVERGED, DOF_LOSS, N_PARAMS, NOT_CONVERGED, TOO_FEW_POINTS
from algorithms.jit import njit, prange
from algorithms.quadric import fit_masked
from algorithms.section import STOPPED, TESTED


@njit(cache=True)
def _untested(active: np.ndarray, score: np.ndarray, critical: np.ndarray) -> None:
    """Points still in a section whose next fit cannot be made are untested (NaN)."""
    for i in range(active.shape[0]):
        if active[i]:
            score[i] = np.nan
            critical[i] = np.nan


@njit(cache=True)
def _plane(xyz: np.ndarray, active: np.ndarray, params: np.ndarray, centroid: np.ndarray) -> None:
    """The plane through the centroid of the active rows across their least spread, as the
    quadric of eq. 18 in the centroid's frame (a7..a9 its unit normal, the rest 0)."""
    n_act = 0
    centroid[:] = 0.0
    for i in range(xyz.shape[0]):
        if active[i]:
            centroid += xyz[i]
            n_act += 1
    centroid /= max(n_act, 1)
    scatter = np.zeros((3, 3))
    for i in range(xyz.shape[0]):
        if active[i]:
            d = xyz[i] - centroid
            scatter += np.outer(d, d)
    _, axes = np.linalg.eigh(scatter)
    params[:] = 0.0
    params[6:9] = axes[:, 0]


@njit(cache=True)
def _one_section(
    xyz: np.ndarray,
    var: np.ndarray,
    crit_table: np.ndarray,
    min_points: int,
    max_fits: int,
    max_iter: int,
    tol: float,
    accelerate: bool,
    score: np.ndarray,
    critical: np.ndarray,
    flagged: np.ndarray,
) -> tuple[int, int, int, bool, bool]:
    """Iterative fit-and-remove on one section's points (n, 3); fills score, critical and
    flagged (n,): each point's T_i (eq. 31) and the critical value t(n' - 9) it was compared
    with, n' the points in that fit.

    Returns (outcome, fits made, adjustment iterations summed over the fits, whether the last
    fit still removed points, i.e. ``max_fits`` ended the refitting, whether the first fit
    started again from the best plane). outcome is TESTED, or
    STOPPED + the quadric fit status that stopped it (TOO_FEW_POINTS when fewer than
    ``min_points`` remain).
    """
    n = xyz.shape[0]
    active = np.ones(n, dtype=np.bool_)
    params = np.empty(N_PARAMS)
    centroid = np.empty(3)
    last_params = np.empty(N_PARAMS)
    last_centroid = np.empty(3)
    v = np.empty(n)
    t = np.empty(n)
    n_active = n
    fits = 0
    iterations = 0
    removed = 0
    from_plane = False
    for _ in range(max_fits):
        if n_active < min_points:
            _untested(active, score, critical)
            return STOPPED + TOO_FEW_POINTS, fits, iterations, False, from_plane
        sigma0, it, status = fit_masked(
            xyz, active, var, max_iter, tol, params, centroid, v, t, accelerate
        )
        fits += 1
        iterations += it
        if status == NOT_CONVERGED:
            # an algebraic start that leads nowhere: a refit starts from the surface it refines,
            # a first fit from the plane that fits the points best (the road of a street)
            if fits == 1:
                _plane(xyz, active, last_params, last_centroid)
                from_plane = True
            sigma0, it, status = fit_masked(
                xyz, active, var, max_iter, tol, params, centroid, v, t, accelerate,
                last_params, last_centroid,
            )
            iterations += it
        if status != CONVERGED:
            _untested(active, score, critical)
            return STOPPED + status, fits, iterations, False, from_plane
        last_params[:] = params
        last_centroid[:] = centroid
        crit = crit_table[n_active - DOF_LOSS]
        removed = 0
        for i in range(n):
            if active[i]:
                score[i] = t[i]
                critical[i] = crit if t[i] == t[i] else np.nan  # NaN T: untested
                if t[i] > crit:
                    flagged[i] = True
                    active[i] = False
                    removed += 1
        n_active -= removed
        if removed == 0:
            break
    return TESTED, fits, iterations, removed > 0, from_plane


@njit(cache=True, parallel=True)
def fit_all_sections(
    xyz: np.ndarray,
    offsets: np.ndarray,
    bucket_offsets: np.ndarray,
    bucket_sections: np.ndarray,
    var: np.ndarray,
    crit_table: np.ndarray,
    min_points: int,
    max_fits: int,
    max_iter: int,
    tol: float,
    accelerate: bool,
    score: np.ndarray,
    critical: np.ndarray,
    flagged: np.ndarray,
    outcome: np.ndarray,
    fits: np.ndarray,
    iterations: np.ndarray,
    capped: np.ndarray,
    from_plane: np.ndarray,
) -> None:
    """Run :func:`_one_section` on xyz[offsets[j]:offsets[j+1]] for every section j in parallel,
    one thread per bucket: bucket b holds the sections bucket_sections[bucket_offsets[b]:
    bucket_offsets[b + 1]] (see :func:`balanced_buckets`)."""
    for b in prange(bucket_offsets.shape[0] - 1):
        for s in range(bucket_offsets[b], bucket_offsets[b + 1]):
            j = bucket_sections[s]
            lo, hi = offsets[j], offsets[j + 1]
            outcome[j], fits[j], iterations[j], capped[j], from_plane[j] = _one_section(
                xyz[lo:hi], var, crit_table, min_points, max_fits, max_iter, tol, accelerate,
                score[lo:hi], critical[lo:hi], flagged[lo:hi],
            )  # fmt: skip
