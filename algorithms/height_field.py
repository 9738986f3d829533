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
   cloud (``"auto"``: the MAD of the full-patch studentised residuals, of a sample of the file's
   points chosen by position with ``sample``, so no error is guessed).

6. *under the lowest surface* (``low``): a return behind the surface its beam crossed is a
   multi-path (mirror) return: a puddle or a window reflects the beam, and the range of the
   longer path puts the point below the road (ASPRS class 7, low noise). Such returns come in
   clumps that form their own surfaces, so steps 1-5 cannot see them; their clumps are apart
   from the real surfaces. The cloud is cut into pieces joined through occupied voxels, at the
   finest voxel size where the real surfaces are whole (:func:`algorithms.detached.
   surface_scale`); the lowest return of each cell (two voxels wide) of the large pieces
   samples the lowest surface where it spans an area (:func:`floor_cells`), and each point
   of a small piece is compared with the floor plane of its 64 nearest cells
   (:func:`algorithms.detached.floor_scores`): its score is how far it lies under the floor,
   in sigmas. Only floors that are ground-like count
   (gradient at most 1, 45 degrees, as ``one_sided``): a mobile scanner sees the road and
   the sidewalks from above, while "the lowest return" of a facade seen over parked cars
   is no floor; there the point is compared with the lowest of those cells instead (a
   clump under everything around it is still low).

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
from algorithms.columns import column_min
from algorithms.params import Parameters, param
from algorithms.result import DetectorResult
from algorithms.stats import MAD_TO_SIGMA, strided_sample

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


def estimate_sigma(terms: np.ndarray, sample: np.ndarray | None = None) -> float:
    """Robust sigma (m): MAD of the full-patch studentised residuals of the rows ``sample``
    (bool, default all; :func:`sigma_sample`)."""
    residuals = studentised_full(terms)
    return sigma_of_residuals([residuals if sample is None else residuals[sample]])


def sigma_sample(position: np.ndarray, file_points: int) -> np.ndarray:
    """(n,) bool: the points ``sigma="auto"`` is estimated from, by their ``position`` in a
    file of ``file_points`` points: every ``max(1, file_points // SIGMA_SAMPLE)``-th. Chosen
    before any residual is known, so a run tile by tile fits the full patches of these points
    alone in its round over the file, and gets the whole run's sample."""
    return position % max(1, file_points // SIGMA_SAMPLE) == 0


def sigma_of_residuals(parts: Iterable[np.ndarray], sample: int = SIGMA_SAMPLE) -> float:
    """:func:`estimate_sigma` of the residuals given in order as ``parts`` (NaN: untested or
    not in the sample), reading each part twice and keeping only the sample: the MAD of every
    ``max(1, finite // sample)``-th finite residual (all of them when they come from
    :func:`sigma_sample`, at most 2 x ``sample``). ``parts`` is called on twice (a list, or
    memory-mapped pieces of a large array)."""
    r = strided_sample(parts, sample)
    if r.size == 0:
        return float("nan")
    return float(MAD_TO_SIGMA * np.median(np.abs(r - np.median(r))))


def full_residuals(xyz: np.ndarray, k: int, origin: np.ndarray | None = None,
                   wanted: np.ndarray | None = None) -> np.ndarray:
    """(n,) full-patch studentised residual of each point (NaN where untested, and outside the
    mask ``wanted`` when given), as ``sigma="auto"`` estimates from them (the points centred
    as :func:`detect_height_field` centres them, neighbours found relative to ``origin`` as
    there)."""
    from algorithms.detached import relative
    from algorithms.height_field_fits import terms_of

    arr = check_xyz(xyz)
    out = np.full(len(arr), np.nan)
    rows = np.arange(len(arr)) if wanted is None else np.flatnonzero(wanted)
    if rows.size == 0:
        return out
    local = arr - arr.mean(axis=0)
    nbr = neighbours(relative(arr, origin), k, rows)
    out[rows] = studentised_full(terms_of(local, nbr, rows, False))
    return out


def neighbours(xyz: np.ndarray, k: int, rows: np.ndarray | None = None) -> np.ndarray:
    """(m, k + 1) indices of the k + 1 nearest points (itself normally first) of each point
    of ``rows`` (default all); equal distances in the points' order
    (:func:`algorithms.detached.nearest_first`), so a tile, whose points are the cloud's in the
    same order and at the same coordinates, picks the whole cloud's neighbours."""
    from algorithms.detached import nearest_first
    from algorithms.neighbours import neighbour_tree

    tree = neighbour_tree(xyz)
    rows = np.arange(len(xyz)) if rows is None else rows
    kk = min(k + 1, len(xyz))
    out = np.empty((rows.size, kk), dtype=np.int64)
    for s in range(0, rows.size, KNN_BATCH):
        batch = xyz[rows[s:s + KNN_BATCH]]
        out[s:s + KNN_BATCH] = nearest_first(tree, batch, kk)[1]
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
    low: bool = param(
        True, "Also score clumps under the lowest ground-like surface around them (multi-path "
        "mirror returns under the road).")
    spacing_xy: float | Literal["auto"] = param(
        "auto", "Metres: the cloud's horizontal point spacing, where the low test's voxel sizes "
        "start, or 'auto' to measure it.", ge=0, le=1000)
    voxel: float | Literal["auto"] = param(
        "auto", "Metres: the voxel size the low test cuts the cloud into pieces at, or 'auto' "
        "for the finest at which the surfaces are whole (reported); 0: none, the low test "
        "scores nothing.", ge=0, le=1000)
    static_dt: float = param(
        0.5, "Seconds: a point of a scattered patch (no surface) with a neighbour within 0.2 m "
        "recorded at least this long before or after it was seen again, a static scatter such "
        "as a tree crown, and is not flagged above the surface when it also lies "
        "static_above over the ground (needs gps_time). 0: off.", ge=0, le=1e6)
    foliage_reach: float = param(
        0.5, "Metres: a point of a scattered patch (no surface) whose k neighbours all lie "
        "within this, more than static_above over the lowest return around it, is in foliage "
        "(a crown the beam enters, even when seen once) and is not flagged above the surface. "
        "Rain, dust and birds in the air are sparser; exhaust and mist hang lower. 0: off.",
        ge=0, le=100)
    static_above: float = param(
        2.0, "Metres: a scatter seen again is vegetation, and not flagged above the surface, "
        "only this far above the lowest return around it (the 3 x 3 cells of 1 m around its "
        "own); exhaust, wheel spray and mist over puddles hang lower, within a vehicle's "
        "height of the road, and are tested even when they persist.", ge=0, le=1000)


#: Metres: how near a point recorded at another moment must lie for ``static_dt``
#: (transient's default radius).
STATIC_RADIUS = 0.2

#: Metres: the cells whose lowest return ``static_above`` measures from; the 3 x 3 cells around
#: a point's own reach at least this far each way and at most 2 sqrt(2) times it.
STATIC_CELL = 1.0
#: XY metres the height over the lowest return around a point reads (a tile's reach).
STATIC_REACH = 2.0 * np.sqrt(2.0) * STATIC_CELL

#: Points per cell a piece needs to be a real surface for the ``low`` test (detached's).
LOW_PIECE_POINTS = 1000
#: Cells of the lowest surface for the floor plane, and its quantile (detached's defaults).
LOW_K_FLOOR = 64
LOW_FLOOR_QUANTILE = 0.05
#: Steepest floor gradient that is ground-like (45 degrees, as ONE_SIDED_NZ).
LOW_MAX_SLOPE = 1.0


#: Of a floor cell's 8 neighbour cells, at least this many hold floor samples that continue
#: its plane (5: a surface seen from above, or its edge; a wall's foot is a line, 2-4).
FLOOR_NEIGHBOURS = 5


def floor_cells(local: np.ndarray, index: np.ndarray, cell: float,
                origin: np.ndarray | None = None) -> np.ndarray:
    """Indices of the lowest returns of ``local[index]`` per ``cell``-metre XY cell
    (:func:`algorithms.detached.lowest_per_cell`, grid corner ``origin`` (2,), default the
    lowest XY of ``local[index]``) that sample a floor: a surface seen from above spans an
    area, so at least FLOOR_NEIGHBOURS of the 8 neighbouring cells hold a lowest return within
    LOW_MAX_SLOPE x their distance in height. The lowest returns of a facade whose foot is
    hidden (by parked cars) form a line: left out.
    """
    from algorithms.detached import grid_index, lowest_per_cell

    if index.size == 0:
        return index
    corner = column_min(local[index, :2]) if origin is None else origin
    lowest = lowest_per_cell(local, index, cell, corner)
    ij = grid_index(local[lowest], cell, corner)
    ij += 1 - column_min(ij)
    width = int(ij[:, 1].max()) + 2
    key = ij[:, 0] * width + ij[:, 1]
    order = np.argsort(key)
    keys, z = key[order], local[lowest[order], 2]
    support = np.zeros(lowest.size, dtype=np.int64)
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            if di == 0 and dj == 0:
                continue
            want = keys + di * width + dj
            pos = np.minimum(np.searchsorted(keys, want), keys.size - 1)
            near = LOW_MAX_SLOPE * cell * np.hypot(di, dj)
            support += (keys[pos] == want) & (np.abs(z[pos] - z) <= near)
    return np.sort(lowest[order[support >= FLOOR_NEIGHBOURS]])


def height_above_lowest(local: np.ndarray, rows: np.ndarray, cell: float = STATIC_CELL
                        ) -> np.ndarray:
    """(m,) how far each point ``rows`` of ``local`` lies above the lowest return of the 3 x 3
    XY cells of ``cell`` metres around its own (grid corner at local's origin, so a tile and
    the whole cloud share the cells): the height of a tree crown over the road beside it."""
    from algorithms.detached import first_lowest_per_key, grid_index

    if rows.size == 0:
        return np.zeros(0)
    ij = grid_index(local, cell, np.zeros(2))
    ij -= column_min(ij) - 1  # a free cell on every side: the 3 x 3 keys never wrap
    width = int(ij[:, 1].max()) + 2
    key = ij[:, 0] * width + ij[:, 1]
    first = first_lowest_per_key(key, local[:, 2])  # in increasing key order
    keys, floor = key[first], local[first, 2]
    lowest = np.full(rows.size, np.inf)
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            want = key[rows] + di * width + dj
            pos = np.minimum(np.searchsorted(keys, want), keys.size - 1)
            lowest = np.where(keys[pos] == want, np.minimum(lowest, floor[pos]), lowest)
    return local[rows, 2] - lowest


def dense_scatter(local: np.ndarray, nbr: np.ndarray, points: np.ndarray, reach: float
                  ) -> np.ndarray:
    """The ``points`` (indices) whose farthest neighbour in ``nbr`` (m, k + 1; their k + 1
    nearest, themselves first) lies within ``reach`` metres."""
    far = np.linalg.norm(local[nbr[:, -1]] - local[points], axis=1)
    return points[far <= reach]


def low_scores(local: np.ndarray, sigma: float, spacing_xy: float | str = "auto",
               voxel: float | str = "auto", sample: np.ndarray | None = None
               ) -> tuple[np.ndarray, dict]:
    """(n,) how many sigmas each point of a small piece lies under the ground-like floor around
    it (step 6 of the module docstring; NaN where untested) and the info. ``local``: the
    points relative to the corner of the voxel and cell grids; ``spacing_xy``, ``voxel``:
    given, or "auto" to measure them here (:func:`sample_spacing` of the points ``sample``
    when given, else :func:`algorithms.detached.xy_spacing`,
    :func:`algorithms.detached.surface_scale`)."""
    from algorithms.detached import floor_scores, small_pieces, voxel_size, xy_spacing

    score = np.full(len(local), np.nan)
    if spacing_xy != "auto":
        horizontal = float(spacing_xy)
    else:
        horizontal = xy_spacing(local) if sample is None else sample_spacing(local, sample)
    size = voxel_size(local, LOW_PIECE_POINTS, horizontal, voxel)
    if size is None:
        return score, {"voxel": None, "points_tested": 0}
    small = small_pieces(local, size, LOW_PIECE_POINTS, np.zeros(3))
    if not small.any():
        return score, {"voxel": size, "points_tested": 0}
    reference = floor_cells(local, np.flatnonzero(~small), 2 * size, np.zeros(2))
    score = floor_scores(local, small, reference, k_floor=LOW_K_FLOOR,
                         quantile=LOW_FLOOR_QUANTILE, below=sigma, reach=4 * size,
                         max_slope=LOW_MAX_SLOPE)
    return score, {"voxel": float(size), "points_tested": int(np.isfinite(score).sum())}


def sample_spacing(local: np.ndarray, sample: np.ndarray) -> float:
    """The low test's horizontal spacing measured on the points of the mask ``sample``
    (:func:`sigma_sample`: by position in the file, so a run tile by tile computes only their
    distances in its round over the file):
    :func:`algorithms.detached.xy_spacing_of_values` of their XY distances to the k-th nearest
    other point of ``local``."""
    from algorithms.detached import xy_kth_distance, xy_spacing_of_values

    return xy_spacing_of_values([xy_kth_distance(local, wanted=sample)])


def detect_height_field(
    xyz: np.ndarray,
    *,
    k: int = 24,
    sigma: float | str = "auto",
    threshold: float = 9.0,
    rms_weight: float = 0.5,
    one_sided: bool = True,
    low: bool = True,
    spacing_xy: float | str = "auto",
    voxel: float | str = "auto",
    origin: np.ndarray | None = None,
    wanted: np.ndarray | None = None,
    sample: np.ndarray | None = None,
    sigma_floor: float = 0.0,
    static_dt: float = 0.5,
    static_above: float = 2.0,
    gps_time: np.ndarray | None = None,
    foliage_reach: float = 0.5,
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
    low : also score small pieces under the lowest ground-like surface (step 6).
    spacing_xy, voxel : the low test's horizontal spacing and voxel size, or "auto" to measure
        them here (a run tile by tile measures them over the whole cloud first).
    origin : (3,) the corner of the low test's voxel and cell grids and of the coordinates
        neighbours are found in (default: the lowest coordinates); runs that share it put a
        point in the same voxels and give it the same neighbours.
    wanted : (n,) bool, the points whose scores are read (default all; a tile's core): the
        patches of the others are not fitted (NaN), and ``sigma="auto"`` comes from these.
    sample : (n,) bool, the points whose full-patch residuals ``sigma="auto"`` and whose XY
        spacing ``spacing_xy="auto"`` are estimated from (default all, and for the spacing a
        regular subsample; :func:`sigma_sample` draws them from a file).
    sigma_floor : metres, the least sigma used, estimated or given (the coordinates' rounding:
        below it a noise-free surface's rounding alone would be flagged; a run tile by tile
        pins an estimate first and floors it as the whole run does).
    static_dt, gps_time : with both (seconds > 0, (n,) seconds), a point whose full patch is
        not one surface and with one of its k nearest within STATIC_RADIUS recorded at least
        ``static_dt`` before or after it was seen again: a static scatter, whose score above
        the surface is capped at the threshold (the low test still applies), when it lies
        more than ``static_above`` metres over the lowest return around it
        (:func:`height_above_lowest`). Transient outliers (dust, exhaust while driving, rain,
        a moving object) are seen once; tree crowns, whose scatter no height field holds, are
        seen again by the next pass or the other scanner; so are a plume fed by the tailpipe
        while the vehicle stands and a mist over a puddle, which hang near the road.
    foliage_reach : metres; a point whose full patch is not one surface, whose k nearest all
        lie within this and which lies more than ``static_above`` over the lowest return around
        it is in foliage, seen once or again: its score above the surface is capped too
        (0: off). The beam enters a crown 5-30 cm and returns from every depth, so a crown's
        scatter is dense; rain, dust and birds in the air are sparse, and exhaust, spray and
        mist hang lower.

    Returns
    -------
    DetectorResult with score (n,) (NaN where fewer than MIN_HALF_POINTS neighbours exist or every
    fit is singular), flagged = score > threshold, critical_value = threshold.
    """
    HeightFieldParameters(k=k, sigma=sigma, threshold=threshold, rms_weight=rms_weight,
                          one_sided=one_sided, low=low, spacing_xy=spacing_xy, voxel=voxel,
                          static_dt=static_dt, static_above=static_above,
                          foliage_reach=foliage_reach)
    from algorithms.height_field_fits import scores_from_terms, seen_again, terms_of

    arr = check_xyz(xyz)
    n = len(arr)
    info: dict = {"k": int(k), "threshold": float(threshold), "rms_weight": float(rms_weight),
                  "one_sided": bool(one_sided), "low": bool(low), "points": int(n)}
    if n == 0:
        info.update(sigma=None, sigma_source="none", points_tested=0, points_flagged=0)
        return DetectorResult(np.zeros(0), np.zeros(0, bool), float(threshold), info)
    from algorithms.detached import relative

    local = arr - arr.mean(axis=0)
    grid_local = relative(arr, origin)  # the same coordinates in a tile: the same neighbours
    rows = np.arange(n) if wanted is None else np.flatnonzero(wanted)
    nbr = neighbours(grid_local, k, rows)
    terms = terms_of(local, nbr, rows, False)  # full patches first: sigma comes from them
    if sigma == "auto":
        sig, source = estimate_sigma(terms, None if sample is None else sample[rows]), "auto"
    else:
        sig, source = float(sigma), "given"
    if sig < sigma_floor:
        sig, source = float(sigma_floor), f"{source}, raised to the coordinates' rounding"
    if not sig > 0:  # a perfect synthetic surface: every residual is rounding
        sig = float(np.finfo(float).eps * max(1.0, float(np.abs(local).max())))
    # the half patches count only where the full patch is not one surface (scores_from_terms)
    edge = ~(terms[:, 0, 2] <= HALF_GATE * sig)
    if edge.any():
        terms[edge] = terms_of(local, nbr[edge], rows[edge])
    static = np.zeros(n, dtype=bool)
    info["points_seen_again_near_ground"] = 0
    if gps_time is not None and static_dt > 0 and edge.any():
        # a scatter that no height field holds (its full patch is not one surface), seen again
        t = np.asarray(gps_time, dtype=np.float64)
        static[rows[edge]] = seen_again(grid_local, t, nbr[edge], rows[edge], STATIC_RADIUS,
                                        float(static_dt))
        again = np.flatnonzero(static)
        low_again = height_above_lowest(grid_local, again) <= static_above
        static[again[low_again]] = False  # near the road: exhaust, spray, mist
        info["points_seen_again_near_ground"] = int(np.count_nonzero(low_again))
    info["points_in_foliage"] = 0
    if foliage_reach > 0 and edge.any():
        foliage = dense_scatter(grid_local, nbr[edge], rows[edge], foliage_reach)
        foliage = foliage[height_above_lowest(grid_local, foliage) > static_above]
        static[foliage] = True
        info["points_in_foliage"] = int(foliage.size)
    del nbr
    score = np.full(n, np.nan)
    score[rows] = scores_from_terms(terms, sig, float(rms_weight),
                                    ONE_SIDED_NZ if one_sided else 2.0, HALF_GATE, MAX_LEVERAGE)
    info["points_static"] = int(np.count_nonzero(static))
    info["points_static_above_threshold"] = int(np.count_nonzero(static & (score > threshold)))
    score[static & (score > threshold)] = threshold  # seen again: not an outlier above
    if low:
        under, info["low_test"] = low_scores(grid_local, sig, spacing_xy, voxel, sample)
        info["low_test"]["points_flagged"] = int(np.count_nonzero(under > threshold))
        score = np.fmax(score, under)  # either test where the other did not apply
    flagged = score > threshold
    info.update(
        sigma=sig, sigma_source=source,
        points_tested=int(np.count_nonzero(~np.isnan(score))),
        points_flagged=int(np.count_nonzero(flagged)),
    )
    return DetectorResult(score=score, flagged=flagged, critical_value=float(threshold), info=info)


# --------------------------------------------------------------------------- tile by tile
#
# As :mod:`algorithms.detached` runs tile by tile (see the notes there): sigma, the horizontal
# spacing (:func:`spacing_with_sigma`) and the voxel size (:func:`voxel_with_sigma`) are
# measured over the whole cloud first, in one round (with sigma given: the spacing, then the
# voxel size); a point's result then depends on its k nearest neighbours, on its piece (the
# piece's extent + 3 voxels while it is small in the region) and, in a small piece, on the
# floor cells within its LOW_K_FLOOR-th nearest one and their 8 neighbours (2 cells, 6 voxels,
# further).

#: The estimates a run tile by tile makes over the whole cloud first, in order.
ESTIMATES = ("sigma", "spacing_xy", "voxel")


def pending_estimate(params: HeightFieldParameters) -> str | None:
    """The first of :data:`ESTIMATES` still "auto" (those of the low test only with ``low``),
    None when all are given."""
    for name in ESTIMATES:
        if getattr(params, name) == "auto" and (name == "sigma" or params.low):
            return name
    return None


def spacing_with_sigma(params: HeightFieldParameters) -> bool:
    """Whether the round that estimates ``sigma`` also measures ``spacing_xy``: both are
    "auto" and come from the same sample, and the XY distance to the 8th nearest other point
    is at most the distance to the k-th (k >= 8) in 3-D, so the residuals' reach covers it."""
    return pending_estimate(params) == "sigma" and params.low and params.spacing_xy == "auto"


def voxel_with_sigma(params: HeightFieldParameters) -> bool:
    """Whether the round that estimates ``sigma`` also cuts the small-piece ladder the voxel
    size is chosen from (the low test on, ``voxel`` "auto"). It is cut from the ladder's
    finest size, :data:`SIGMA_ROUND_LADDER_START`: the ladder of any start is a suffix of that
    one (:func:`algorithms.detached.voxel_ladder`), so the spacing that trims it need not be
    known until the round is pinned (:func:`pin_sigma_round`)."""
    return pending_estimate(params) == "sigma" and params.low and params.voxel == "auto"


#: Where the ladder of the round that estimates ``sigma`` starts (:func:`voxel_with_sigma`).
SIGMA_ROUND_LADDER_START = 0.0


def sigma_round_columns(params: HeightFieldParameters) -> list[str]:
    """The values of each point in the round that estimates ``sigma``, in column order:
    ``residual``, then ``xy_distance`` (:func:`spacing_with_sigma`), then ``ladder``
    (:func:`voxel_with_sigma`)."""
    return ["residual", *(["xy_distance"] if spacing_with_sigma(params) else []),
            *(["ladder"] if voxel_with_sigma(params) else [])]


def estimate_values(xyz: np.ndarray, params: HeightFieldParameters,
                    origin: np.ndarray | None, wanted: np.ndarray | None = None,
                    ladder: np.ndarray | None = None) -> np.ndarray:
    """(n,) each point's value for the pending estimate: its full-patch residual
    (:func:`full_residuals`), its XY distance to its 8th neighbour
    (:func:`algorithms.detached.xy_kth_distance`) or its small-piece bits
    (:func:`algorithms.detached.small_ladder`); the first two only for the points of the mask
    ``wanted`` when given (NaN elsewhere). (n, m) in the round that estimates ``sigma`` with
    others: the columns of :func:`sigma_round_columns` (the bits for every point).
    ``ladder``: the bits of :data:`SIGMA_ROUND_LADDER_START`'s ladder when already cut."""
    from algorithms.detached import ladder_pieces, relative, xy_kth_distance

    name = pending_estimate(params)
    if name == "sigma":
        columns = [full_residuals(xyz, params.k, origin, wanted)]
        if spacing_with_sigma(params):
            columns.append(xy_kth_distance(relative(check_xyz(xyz), origin), wanted=wanted))
        if voxel_with_sigma(params):
            columns.append(ladder if ladder is not None else ladder_pieces(
                relative(check_xyz(xyz), origin), LOW_PIECE_POINTS,
                SIGMA_ROUND_LADDER_START)[0])
        return columns[0] if len(columns) == 1 else np.column_stack(columns)
    local = relative(check_xyz(xyz), origin)
    if name == "spacing_xy":
        return xy_kth_distance(local, wanted=wanted)
    if name == "voxel":
        return ladder_pieces(local, LOW_PIECE_POINTS, float(params.spacing_xy))[0]
    raise ValueError("every estimate of these parameters is given")


def pin_sigma_round(params: HeightFieldParameters, parts: list[np.ndarray]
                    ) -> tuple[HeightFieldParameters, dict]:
    """The parameters with what the round that estimates ``sigma`` measured fixed from every
    point's values (:func:`sigma_round_columns`), as the whole cloud's run measures them:
    sigma, then the spacing, then the voxel size from the ladder trimmed at that spacing (left
    "auto" for a round of its own when the spacing lies beyond the ladder); and the note."""
    from dataclasses import replace

    from algorithms.detached import LARGEST_VOXEL, scale_of_ladder, xy_spacing_of_values

    columns = sigma_round_columns(params)

    def column(name: str) -> list[np.ndarray]:
        c = columns.index(name)
        return [p[:, c] if p.ndim == 2 else p for p in parts]

    sigma = sigma_of_residuals(column("residual"))
    if not sigma > 0:  # as detect_height_field: a perfect surface leaves rounding only
        sigma = float(np.finfo(float).eps)
    pinned = replace(params, sigma=sigma)
    if "xy_distance" in columns:
        pinned = replace(pinned, spacing_xy=xy_spacing_of_values(column("xy_distance")))
    if "ladder" in columns and pinned.spacing_xy != "auto":
        start = float(pinned.spacing_xy)
        if start <= LARGEST_VOXEL:
            pinned = replace(pinned, voxel=scale_of_ladder(
                column("ladder"), LOW_PIECE_POINTS, start, SIGMA_ROUND_LADDER_START))
    return pinned, {"sigma": sigma, "sigma_source": "auto"}


def pin_low_estimate(params: HeightFieldParameters,
                     parts: list[np.ndarray]) -> tuple[HeightFieldParameters, dict]:
    """The parameters with the low test's pending estimate (``spacing_xy`` or ``voxel``) fixed
    from every point's value, as the whole cloud's run measures it, and the note on it."""
    from dataclasses import replace

    from algorithms.detached import scale_of_ladder, xy_spacing_of_values

    name = pending_estimate(params)
    if name == "spacing_xy":
        return replace(params, spacing_xy=xy_spacing_of_values(parts)), {}
    if name == "voxel":
        value = scale_of_ladder(parts, LOW_PIECE_POINTS, float(params.spacing_xy))
        return replace(params, voxel=value), {}
    raise ValueError(f"height_field's {name} is not the low test's")


def tile_reach(xyz: np.ndarray, params: HeightFieldParameters, where: np.ndarray,
               origin: np.ndarray | None, allowed: np.ndarray | None = None,
               sample: np.ndarray | None = None,
               ladder: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """(n,) XY metres around each point of the mask ``where`` (others: 0) its result, or with
    an estimate pending its value, depended on in this cloud (a region of a larger one).
    ``allowed`` (n,): the reach each point may have; a neighbourhood known to lie within it
    may be reported by that bound (:func:`algorithms.tiles.kth_distance_within`).
    In the round that estimates ``sigma``: the residuals and distances are those of the points
    of the mask ``sample`` alone (default all), the ladder's bits (:func:`voxel_with_sigma`)
    every point's; ``ladder``: (bits, reach) of :data:`SIGMA_ROUND_LADDER_START`'s ladder
    when already cut."""
    from scipy.spatial import cKDTree

    from algorithms.detached import (
        XY_SPACING_K,
        ladder_pieces,
        piece_reach,
        reach_through,
        relative,
        voxel_size,
    )
    from algorithms.tiles import kth_distance_within

    arr = check_xyz(xyz)
    n = len(arr)
    out = np.zeros(n)
    if not where.any():
        return out
    name = pending_estimate(params)
    local = relative(arr, origin)
    if name == "spacing_xy":
        return kth_distance_within(local[:, :2], XY_SPACING_K + 1, where, allowed)
    if name == "voxel":
        reach = ladder_pieces(local, LOW_PIECE_POINTS, float(params.spacing_xy))[1]
        return np.where(where, reach, 0.0)
    kk = params.k + 1  # the point itself and its k neighbours
    if name == "sigma":
        out = kth_distance_within(local, kk, where if sample is None else where & sample,
                                  allowed)
        if voxel_with_sigma(params):
            cut = ladder if ladder is not None else ladder_pieces(
                local, LOW_PIECE_POINTS, SIGMA_ROUND_LADDER_START)
            out = np.maximum(out, np.where(where, cut[1], 0.0))
        return out
    if n < kk:
        return np.where(where, np.inf, 0.0)
    out = kth_distance_within(local, kk, where, allowed)
    if name is None and (params.static_dt > 0 or params.foliage_reach > 0):
        # a scatter seen again or in foliage: the lowest return around
        out = np.maximum(out, STATIC_REACH)
    if name is None and params.low:
        size = voxel_size(local, LOW_PIECE_POINTS, float(params.spacing_xy), params.voxel)
        if size is not None:
            around = piece_reach(local, size, LOW_PIECE_POINTS)
            out = np.maximum(out, around)
            small = np.flatnonzero((around > 0) & where)
            if small.size:
                reference = floor_cells(local, np.flatnonzero(around == 0), 2 * size,
                                        np.zeros(2))
                if reference.size < LOW_K_FLOOR:
                    out[small] = np.inf
                else:
                    d, _ = cKDTree(local[reference, :2]).query(local[small, :2],
                                                               k=[LOW_K_FLOOR])
                    cells = d[:, 0] + 6 * size  # a cell's 8 neighbours: 2 cells further
                    out[small] = np.maximum(out[small],
                                            reach_through(local, small, cells, around))
    return np.where(where, out, 0.0)
