"""The `section` detector: algorithm (c) of Leslar, Wang & Hu (2010).

The cloud is cut into square XY sections of ``section_size`` metres (grid anchored at the
lower-left corner of the cloud's bounding box, or at a given ``anchor``). One quadric (eqs. 18-31,
:mod:`algorithms.quadric`) is fitted per section; the points whose T_i (eq. 31) exceeds the
two-sided critical value of t(n - 9), n the points still in the section, are removed together and
the surface is fitted again from a fresh algebraic start, until a fit removes nothing or
``max_iterations`` fits were made. A refit whose algebraic start does not converge starts again
from the surface of the fit before it (moved to the new centroid): the surface it refines; a
first fit whose algebraic start does not converge (a section of road, wall and car the quadric
cannot hold, where the iteration wanders between surfaces) starts again from the plane that
fits the points best, as a quadric (the road, in a street). Where that does not converge either
(the iteration has no fixed point it can reach: on one 5 m street section of road, walls and
a vehicle, 31 k points, it wanders from both starts on some CPUs and converges on others, as
the last bits of its sums differ), the section is cut in four on the same grid and each
quarter is fitted afresh, its earlier fits discarded, at most ``MAX_SPLITS`` times; the
statistics report how many sections were cut.

Scores: a removed point keeps the T_i of the fit that removed it; a kept point gets its T_i in the
last fit. A section that has fewer than the points needed for eq. 31 to flag anything at ``alpha``
(see :func:`algorithms.fit_outcome.min_patch_size`; never fewer than 10), or whose fit does not
converge, leaves its remaining points untested (NaN); points removed before stay flagged.
Sections run in parallel (numba; the sections are shared among the threads by size).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from algorithms.checks import check_xyz
from algorithms.columns import column_min
from algorithms.fit_outcome import DOF_LOSS, NOT_CONVERGED, min_patch_size
from algorithms.params import Parameters, param
from algorithms.patch import SIGMA_DOC, UNTESTED_REASONS, Sigma, sigma_axes, untested_reasons
from algorithms.result import DetectorResult
from algorithms.stats import t_critical_value
from algorithms.tiles import group_by_cell

#: Adjustments per fit at most (over all stages, :func:`algorithms.quadric.stage_budget`) and the
#: convergence tolerance on ||da||. A section holds thousands of points of several surfaces (a
#: wall, the road, a tree): its fits take far more adjustments than a patch's; at 500, one
#: section of 35 k points in a 5 m section of a simulated street left its points untested.
FIT_MAX_ITER = 2000
FIT_TOL = 1e-8
#: Times a section whose fit does not converge from either start is cut in four at most (a
#: 5 m section down to 0.625 m quarters); its points stay untested after the last.
MAX_SPLITS = 3


@dataclass(frozen=True)
class SectionParameters(Parameters):
    """Algorithm (c): one quadric per square XY section, refitted until no outlier remains."""

    section_size: float = param(5.0, "Section edge in metres.", gt=0, le=10000)
    sigma: Sigma = param(0.005, SIGMA_DOC, gt=0)
    alpha: float = param(0.001, "Two-sided significance level.", gt=0, lt=0.5)
    max_iterations: int = param(10, "Refits per section at most.", ge=1, le=1000)


#: Section outcome: every remaining point tested (no outlier left, or ``max_iterations`` fits).
TESTED = 0
#: Section outcome: the last fit stopped for the reason of its fit status (algorithms.quadric);
#: the section's remaining points are untested. Codes 1 + status.
STOPPED = 1


def balanced_buckets(sizes: np.ndarray, n_buckets: int) -> tuple[np.ndarray, np.ndarray]:
    """Sections shared among ``n_buckets`` threads with about equal points each (greedy, largest
    section first to the least loaded bucket).

    numba's prange splits its range into equal contiguous parts, and section costs differ by
    orders of magnitude (a mobile strip is a few sections wide), so one part per thread is made
    here. Returns (offsets (n_buckets + 1,), sections): bucket b is sections[offsets[b]:
    offsets[b + 1]]. The result never depends on it: every section is fitted on its own.
    """
    n_buckets = max(1, min(int(n_buckets), sizes.size))
    load = np.zeros(n_buckets, dtype=np.int64)
    owner = np.empty(sizes.size, dtype=np.int64)
    for j in np.argsort(-sizes, kind="stable"):
        b = int(np.argmin(load))
        owner[j] = b
        load[b] += sizes[j]
    sections = np.argsort(owner, kind="stable")
    offsets = np.searchsorted(owner[sections], np.arange(n_buckets + 1))
    return offsets.astype(np.int64), sections.astype(np.int64)


def section_cells(xy: np.ndarray, size: float) -> np.ndarray:
    """(n,) int64 label of each point's square section of a grid starting at XY (0, 0)."""
    if xy.shape[0] == 0:
        return np.zeros(0, dtype=np.int64)
    ij = np.floor(xy / size).astype(np.int64)
    ij -= column_min(ij)  # points left of the anchor get their own sections
    return ij[:, 1] * (int(ij[:, 0].max()) + 1) + ij[:, 0]


def detect_section(
    xyz: np.ndarray,
    *,
    section_size: float = 5.0,
    sigma: float | np.ndarray = 0.005,
    alpha: float = 0.001,
    max_iterations: int = 10,
    accelerate: bool = True,
    anchor: np.ndarray | None = None,
) -> DetectorResult:
    """Fit one quadric per square XY section and remove outliers iteratively.

    Parameters
    ----------
    xyz : (n, 3) float
        Coordinates in metres (any offset; each section is centred on its own centroid).
    section_size : float
        Section edge in metres.
    sigma : float or (3,) float
        Coordinate standard deviation, D_ii = diag(sigma^2) of eq. 30.
    alpha : float
        Two-sided significance level of the t test of eq. 31 (critical value t(n - 9), n the
        points in the fit).
    max_iterations : int
        Fits per section at most.
    accelerate : bool
        Begin each fit with the Anderson-accelerated stage (:func:`algorithms.quadric.
        fit_quadrics`); False takes the plain path with damped restarts only. Both reach the same
        fixed points, but a fit that has several may end in another one; the accelerated path
        converges on more sections (65 % of the points of a simulated mobile cloud tested
        against 35 %).
    anchor : (2,) float, optional
        XY corner where the grid of sections starts, in the frame of ``xyz`` (default: the
        lower-left corner of the points), so that a part of a cloud keeps the whole's sections.

    Returns
    -------
    DetectorResult
        score (n,) T_i (eq. 31) at removal or in the final fit, NaN where untested;
        flagged (n,) points removed as outliers; ``critical_value`` (n,) the t(n' - 9) each
        point's T_i was compared with (n' the points in that fit; NaN where untested), so that
        flagged == (score > critical_value) point by point.
    """
    SectionParameters(section_size=section_size, sigma=sigma, alpha=alpha,
                      max_iterations=max_iterations)
    pts = check_xyz(xyz)
    var = sigma_axes(sigma) ** 2
    n = pts.shape[0]
    min_points = max(min_patch_size(alpha), DOF_LOSS + 1)

    corner = column_min(pts) if n else np.zeros(3)
    if anchor is not None:  # z too stays put: a tile computes with the whole cloud's numbers
        corner = np.r_[np.asarray(anchor, dtype=np.float64), 0.0]
    local = pts - corner
    runs = fit_with_quarters(local, float(section_size), var, alpha, min_points,
                             int(max_iterations), bool(accelerate))
    score, critical, flagged, point_outcome = merged_runs(runs, n)
    info = {
        "section_size": float(section_size),
        "sigma": float(np.sqrt(var[0])) if np.all(var == var[0]) else np.sqrt(var).tolist(),
        "alpha": float(alpha),
        "max_iterations": int(max_iterations),
        **_run_statistics(runs, score, point_outcome, alpha, min_points),
        "fit_max_iterations": FIT_MAX_ITER,
        "fit_tolerance": FIT_TOL,
    }
    return DetectorResult(score, flagged, critical, info)


def fit_with_quarters(local: np.ndarray, size: float, var: np.ndarray, alpha: float,
                      min_points: int, max_iterations: int, accelerate: bool
                      ) -> list[SectionRun]:
    """:func:`fit_sections` at ``size``, then again on the points of every section whose fit
    converged from neither start, in sections half as wide (the same grid cut in four), at
    most :data:`MAX_SPLITS` times. Each run's ``rows``: its points' positions in ``local``."""
    runs = []
    rows = np.arange(local.shape[0])
    for splits in range(MAX_SPLITS + 1):
        run = fit_sections(local[rows], size, var, alpha, min_points, max_iterations, accelerate)
        run.rows = rows
        runs.append(run)
        wandered = run.outcome == STOPPED + NOT_CONVERGED
        if splits == MAX_SPLITS or not wandered.any():
            break
        run.split = wandered
        rows = rows[run.points_of(wandered)]
        size /= 2.0
    return runs


def merged_runs(runs: list[SectionRun], n: int
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(n,) score, critical value, flag and section outcome of each point from the last run
    that fitted it (a cut section's quarters replace it)."""
    score = np.full(n, np.nan)
    critical = np.full(n, np.nan)
    flagged = np.zeros(n, dtype=bool)
    outcome = np.full(n, TESTED)
    for run in runs:
        score[run.rows], critical[run.rows], flagged[run.rows] = (
            run.score, run.critical, run.flagged)
        outcome[run.rows] = run.point_outcome()
    return score, critical, flagged, outcome


def _run_statistics(runs: list[SectionRun], score: np.ndarray, point_outcome: np.ndarray,
                    alpha: float, min_points: int) -> dict:
    """The statistics of the sections, their quarters and their fits."""
    tested = ~np.isnan(score)
    reasons = untested_reasons()
    for code, name in UNTESTED_REASONS.items():
        reasons[name] += int(np.count_nonzero(~tested & (point_outcome == STOPPED + code)))
    # T_i distrusted in a converged fit (cancellation in q_vv): degenerate geometry too.
    reasons["degenerate_geometry"] += int(np.count_nonzero(~tested & (point_outcome == TESTED)))
    m = runs[0].outcome.size
    median_n = int(np.median(runs[0].sizes)) if m else 0
    fits = np.concatenate([r.fits for r in runs])
    n_fits = int(fits.sum())
    return {
        "critical_value": float(t_critical_value(alpha, median_n - DOF_LOSS))
        if median_n > 9 else None,
        "critical_value_note": "t(n-9) of each fit, n the points in it; the value shown is for "
                               "the median section's first fit",
        "min_points_per_section": int(min_points),
        "sections": int(m),
        "sections_cut_in_four": int(sum(np.count_nonzero(r.split) for r in runs)),
        "smallest_section_size": runs[-1].size,
        "sections_untested": _sections_by_reason(
            np.concatenate([r.outcome[~r.split] for r in runs])),
        "points_tested": int(tested.sum()),
        "points_untested": reasons,
        "fits": n_fits,
        "max_fits_per_section": int(fits.max()) if fits.size else 0,
        "mean_fits_per_section": n_fits / fits.size if fits.size else None,
        "sections_stopped_at_max_iterations": int(sum(np.count_nonzero(r.capped) for r in runs)),
        "sections_started_from_plane": int(sum(np.count_nonzero(r.from_plane) for r in runs)),
        "mean_iterations": float(sum(int(r.iterations.sum()) for r in runs)) / n_fits
        if n_fits else None,
    }


@dataclass
class SectionRun:
    """One pass of fit-and-remove over a grid of sections of edge ``size``: per point (in the
    order of the points given) score, critical value and flag; per section (in label order)
    its point count, outcome, fits, adjustment iterations, whether ``max_iterations`` ended it
    and whether its first fit started again from the plane; ``split``: the sections cut in
    four for the next pass; ``rows``: where the points given lie in the caller's array."""

    size: float
    order: np.ndarray
    sizes: np.ndarray
    score: np.ndarray
    critical: np.ndarray
    flagged: np.ndarray
    outcome: np.ndarray
    fits: np.ndarray
    iterations: np.ndarray
    capped: np.ndarray
    from_plane: np.ndarray
    split: np.ndarray
    rows: np.ndarray | None = None

    def point_outcome(self) -> np.ndarray:
        """(n,) the outcome of each point's section."""
        out = np.empty(self.order.size, dtype=np.int64)
        out[self.order] = np.repeat(self.outcome, self.sizes)
        return out

    def points_of(self, sections: np.ndarray) -> np.ndarray:
        """Positions (into the points given) of the points of the sections of the mask."""
        return np.sort(self.order[np.repeat(sections, self.sizes)])


def fit_sections(local: np.ndarray, size: float, var: np.ndarray, alpha: float,
                 min_points: int, max_iterations: int, accelerate: bool) -> SectionRun:
    """Fit-and-remove (eqs. 18-31) on every square section of ``size`` metres of ``local``
    (n, 3; grid corner at XY (0, 0)), all sections in parallel."""
    n = local.shape[0]
    order, offsets = group_by_cell(section_cells(local[:, :2], size))
    sizes = np.diff(offsets)
    max_n = int(sizes.max()) if sizes.size else 0
    crit_table = np.full(max(max_n - DOF_LOSS + 1, 1), np.nan)
    if max_n > DOF_LOSS:
        crit_table[1:] = t_critical_value(alpha, np.arange(1, max_n - DOF_LOSS + 1))
    m = sizes.size
    xyz_sorted = np.ascontiguousarray(local[order])
    score_sorted = np.full(n, np.nan)
    critical_sorted = np.full(n, np.nan)
    flagged_sorted = np.zeros(n, dtype=np.bool_)
    run = SectionRun(size, order, sizes, np.empty(n), np.empty(n), np.empty(n, dtype=bool),
                     np.zeros(m, dtype=np.int64), np.zeros(m, dtype=np.int64),
                     np.zeros(m, dtype=np.int64), np.zeros(m, dtype=np.bool_),
                     np.zeros(m, dtype=np.bool_), np.zeros(m, dtype=bool))
    if m:
        import numba

        from algorithms.section_fits import fit_all_sections

        bucket_offsets, bucket_sections = balanced_buckets(sizes, numba.get_num_threads())
        fit_all_sections(
            xyz_sorted, offsets, bucket_offsets, bucket_sections, var, crit_table, min_points,
            max_iterations, FIT_MAX_ITER, FIT_TOL, accelerate, score_sorted, critical_sorted,
            flagged_sorted, run.outcome, run.fits, run.iterations, run.capped, run.from_plane,
        )  # fmt: skip
    run.score[order] = score_sorted
    run.critical[order] = critical_sorted
    run.flagged[order] = flagged_sorted
    return run


def _sections_by_reason(outcome: np.ndarray) -> dict[str, int]:
    """Sections whose refitting stopped with points untested, by the reason of the fit that
    stopped it (the names of :func:`algorithms.patch.untested_reasons`)."""
    out = untested_reasons()
    for code, name in UNTESTED_REASONS.items():
        out[name] += int(np.count_nonzero(outcome == STOPPED + code))
    return out
