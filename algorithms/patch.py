"""The `patch` detector: algorithm (b) of Leslar, Wang & Hu (2010), eqs. 18-31.

For every point the general quadric (eqs. 18-19) is fitted to its k nearest neighbours (the point
itself included) by the adjustment of :mod:`algorithms.quadric`, and the point's own T_i (eq. 31)
is tested against the two-sided critical value of t(k - 9) at ``alpha``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from algorithms.checks import check_xyz
from algorithms.columns import column_min
from algorithms.errors import ParameterError
from algorithms.fit_outcome import (
    COLLINEAR,
    CONVERGED,
    DOF_LOSS,
    NOT_CONVERGED,
    SINGULAR,
    TOO_FEW_POINTS,
    min_patch_size,
)
from algorithms.params import Parameters, param
from algorithms.result import DetectorResult
from algorithms.stats import t_critical_value
from algorithms.tiles import spatial_batches

#: Patches fitted per batch (for k = 40: 65536 x 40 x 3 float64 = 63 MB of gathered coordinates);
#: larger k gets proportionally smaller batches, so memory does not grow with k.
BATCH_POINTS = 65536
BATCH_NEIGHBOURS = BATCH_POINTS * 40
#: Adjustments per patch at most (over all stages of the iteration, see
#: :func:`algorithms.quadric.stage_budget`), and the step size taken as convergence (||da||,
#: ||a|| = 1). T_i lies within ~100 tol of its limit, and the accelerated path is sensitive to
#: rounding (coordinates near 5e6 m move a stopped T_i by up to ~100 tol too): 1e-8 keeps scores
#: of a shifted cloud within 1e-5 of each other; 1e-6 would save ~5 adjustments per patch.
FIT_MAX_ITER = 500
FIT_TOL = 1e-8

#: Coordinates up to this many metres are taken as local and used as they are.
LOCAL_EXTENT = 1e5
#: Larger coordinates are shifted by a multiple of this many metres.
SHIFT_GRID = 65536.0

#: Why a point is untested, by fit status (:mod:`algorithms.quadric`), as named in the statistics.
UNTESTED_REASONS = {
    NOT_CONVERGED: "did_not_converge",
    COLLINEAR: "degenerate_geometry",
    SINGULAR: "degenerate_geometry",
    TOO_FEW_POINTS: "too_few_points",
}


#: Coordinate standard deviation: one number, or one per axis (X, Y, Z).
Sigma = float | tuple[float, float, float]
SIGMA_DOC = ("Coordinate standard deviation in metres, one number or one per axis (D_ii = "
             "diag(sigma^2) in eq. 30).")


@dataclass(frozen=True)
class PatchParameters(Parameters):
    """Algorithm (b): quadric (eqs. 18-31) fitted to the k nearest neighbours of each point."""

    k: int = param(40, "Neighbours per patch, the point itself included.", ge=10, le=500)
    sigma: Sigma = param(0.005, SIGMA_DOC, gt=0)
    alpha: float = param(0.001, "Two-sided significance level.", gt=0, lt=0.5)

    def check(self) -> None:
        check_k_alpha(self.k, self.alpha)


def sigma_axes(sigma: Sigma) -> np.ndarray:
    """A declared sigma as a (3,) array of per-axis standard deviations."""
    return np.broadcast_to(np.asarray(sigma, dtype=np.float64), (3,)).copy()


def check_k_alpha(k: int, alpha: float) -> float:
    """Critical value t(k - 9) at ``alpha``; ParameterError when eq. 31 can never exceed it."""
    crit = t_critical_value(alpha, k - DOF_LOSS)
    if not np.sqrt(k - DOF_LOSS) > crit:
        raise ParameterError(
            f"k={k} is too small for alpha={alpha}: T of eq. 31 never exceeds "
            f"sqrt(k-9)={np.sqrt(k - DOF_LOSS):.3g} < t(k-9)={crit:.3g}, so nothing could be "
            f"flagged; use k >= {min_patch_size(alpha)} or a larger alpha"
        )
    return float(crit)


def distinct_locations(xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The first point at each distinct location, and each point's location.

    Returns first (u,) row indices (in order of location) and location (n,) with
    ``xyz[first[location]] == xyz``. Points at one location share their patch: the k-d tree
    returns the same neighbours for the same query coordinates, so the fit and the point's
    T_i (eq. 31) are the same numbers (mobile clouds repeat points while the vehicle stands).
    """
    order = np.lexsort(xyz.T[::-1])
    ordered = xyz[order]
    new = np.ones(order.size, dtype=bool)
    new[1:] = np.any(ordered[1:] != ordered[:-1], axis=1)
    location = np.empty(order.size, dtype=np.int64)
    location[order] = np.cumsum(new) - 1
    return order[new], location


def frame_shift(xyz: np.ndarray) -> np.ndarray:
    """(3,) what to subtract from the coordinates before any arithmetic: nothing for
    coordinates already local (below ``LOCAL_EXTENT`` metres: the cloud types of this project),
    else the minimum corner floored to a multiple of ``SHIFT_GRID`` metres. A tile of a cloud
    and the whole cloud then subtract the same numbers, so their patches hold the same bits
    and give the same scores (a shift to each one's own minimum corner would round
    differently)."""
    if not xyz.size or float(np.abs(xyz).max()) <= LOCAL_EXTENT:
        return np.zeros(3)
    return np.floor(column_min(xyz) / SHIFT_GRID) * SHIFT_GRID


def detect_patch(
    xyz: np.ndarray,
    *,
    k: int = 40,
    sigma: float | np.ndarray = 0.005,
    alpha: float = 0.001,
    batch_points: int = BATCH_POINTS,
    tile_size: float | None = None,
) -> DetectorResult:
    """Test every point against the quadric fitted to its k nearest neighbours.

    Parameters
    ----------
    xyz : (n, 3) float
        Coordinates in metres (any offset: the cloud is shifted to its minimum corner and every
        patch to its own centroid before any polynomial arithmetic).
    k : int
        Points per patch, the tested point included (>= 10 and large enough for ``alpha``).
    sigma : float or (3,) float
        Coordinate standard deviation in metres, D_ii = diag(sigma^2) in eq. 30. T_i does not
        depend on a common scale of sigma (sigma_0 absorbs it); only per-axis ratios matter.
    alpha : float
        Two-sided significance level of the t test of eq. 31.
    batch_points, tile_size :
        Memory control: patches are gathered and fitted for ``batch_points`` spatially adjacent
        points at a time. Results do not depend on them.

    Returns
    -------
    DetectorResult
        score (n,) = T_i of eq. 31 of each point in its own patch, NaN where untested;
        flagged = score > t(k - 9). ``info["points_untested"]`` counts the untested points by
        reason (:func:`untested_reasons`); ``info["points_tested_a_priori"]`` the points whose
        patch the quadric holds exactly, tested with the a-priori variance factor
        (:func:`algorithms.quadric.t_statistic`: their score is near 0).
    """
    p = PatchParameters(k=k, sigma=sigma, alpha=alpha)
    pts = check_xyz(xyz)
    var_sigma = sigma_axes(p.sigma)
    k = int(k)
    crit = check_k_alpha(k, float(alpha))
    n = pts.shape[0]
    score = np.full(n, np.nan)
    reasons = untested_reasons()
    info: dict = {
        "k": k,
        "sigma": float(var_sigma[0]) if np.all(var_sigma == var_sigma[0]) else var_sigma.tolist(),
        "alpha": float(alpha),
        "critical_value": crit,
        "points_tested": 0,
        "points_tested_a_priori": 0,
        "points_untested": reasons,
        "mean_iterations": None,
        "fit_max_iterations": FIT_MAX_ITER,
        "fit_tolerance": FIT_TOL,
    }
    if n < k:
        reasons["too_few_points"] = n
        info["note"] = f"fewer points ({n}) than k={k}: nothing tested"
        return DetectorResult(score, np.zeros(n, dtype=bool), crit, info)

    from algorithms.neighbours import nearest_in_order, neighbour_tree
    from algorithms.quadric import EXACT_FIT_SIGMA0, fit_quadrics

    local = pts - frame_shift(pts)  # the same numbers for any subset of the same cloud
    tree = neighbour_tree(local)
    first, location = distinct_locations(local)
    copies = np.bincount(location)  # points at each distinct location
    location_score = np.full(first.size, np.nan)
    location_status = np.empty(first.size, dtype=np.int64)
    location_exact = np.zeros(first.size, dtype=bool)  # a fit through every point
    iterations_sum = 0
    batch_points = max(1, min(int(batch_points), BATCH_NEIGHBOURS // k))
    for batch in spatial_batches(local[first, :2], batch_points, tile_size):
        nbr = nearest_in_order(tree, local, first[batch], k)
        fit = fit_quadrics(
            local, var_sigma, neighbours=nbr, max_iter=FIT_MAX_ITER, tol=FIT_TOL,
            t_first_only=True,
        )
        location_score[batch] = np.where(fit.converged, fit.t_stat[:, 0], np.nan)
        location_status[batch] = fit.status
        location_exact[batch] = fit.converged & (fit.sigma0 <= EXACT_FIT_SIGMA0)
        iterations_sum += int((copies[batch] * fit.iterations).sum())  # per point, not location
        del nbr, fit
    score = location_score[location]
    tested = ~np.isnan(score)
    count_untested(reasons, location_status[location], tested)
    info["points_tested"] = int(tested.sum())
    info["points_tested_a_priori"] = int(np.count_nonzero(location_exact[location] & tested))
    info["mean_iterations"] = iterations_sum / n
    flagged = np.zeros(n, dtype=bool)
    flagged[tested] = score[tested] > crit
    return DetectorResult(score, flagged, crit, info)


def untested_reasons() -> dict[str, int]:
    """Untested points by reason, all zero: ``did_not_converge`` (the iteration of eqs. 20-29 did
    not reach the tolerance in ``FIT_MAX_ITER`` adjustments), ``degenerate_geometry`` (nearly
    collinear points, singular normal equations, or a T_i beyond the bound sqrt(n - 9) that
    cancellation in q_vv produced) and ``too_few_points`` (fewer points than the fit needs)."""
    return {"did_not_converge": 0, "degenerate_geometry": 0, "too_few_points": 0}


def count_untested(reasons: dict[str, int], status: np.ndarray, tested: np.ndarray) -> None:
    """Add the untested points (not ``tested``) to ``reasons`` by their fit ``status``: a
    converged fit whose T_i is NaN (distrusted, :func:`algorithms.quadric.t_statistic`) counts as
    degenerate geometry."""
    untested = status[~tested]
    counts = np.bincount(untested, minlength=max(UNTESTED_REASONS) + 1)
    for code, name in UNTESTED_REASONS.items():
        reasons[name] += int(counts[code])
    reasons["degenerate_geometry"] += int(counts[CONVERGED])
