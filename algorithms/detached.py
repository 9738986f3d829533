"""Gross outliers of airborne clouds: returns detached from the surface, above or below it.

An airborne laser looks down: every real return lies on or above the terrain, which is one
continuous surface, and nothing real floats far above everything else. Three tests follow
from that, each comparing a return with surfaces it is not part of, so that outliers in clumps
cannot hide each other:

1. **Small clusters** (high and low). The connected components of the graph that links points
   closer than max(``link``, ``link_spacing`` x the cloud's median nearest-neighbour distance)
   metres; a component of at most ``max_cluster`` points is a candidate cluster (computed
   exactly from each point's ``max_cluster`` nearest neighbours, see :func:`small_clusters`).
   For each candidate point, the ``k_surface`` nearest non-candidate points in XY get a
   least-squares plane (centred, so the slope of steep terrain is taken out); the candidate
   scores max((lowest - r) / ``below``, (r - highest) / ``above``) where r is its residual and
   lowest/highest are those surface points' own extreme residuals (:func:`envelope_scores`).
   ``above`` is large (10 m) because real objects sparse enough to form small clusters (a lone
   tree crown, a wire) stand metres over the ground; birds and atmospheric returns stand tens
   of metres over it.
2. **Pieces under the lowest surface** (low). Low noise (ASPRS class 7: multipath and early
   triggers, the commonest noise class of real deliveries) comes in clumps of tens to hundreds
   of returns, metres to tens of metres under the ground, too many for test 1. The cloud is cut
   into pieces of points joined through occupied neighbouring voxels (:func:`voxel_pieces`), at
   the finest voxel size where at most 1 % of the points lie in pieces of fewer than
   ``piece_points`` points (:func:`surface_scale`): the real surfaces are then whole and the
   clumps apart. The lowest point of each cell (two voxels wide) of the large pieces samples the
   lowest surface; for each point of a small piece, the plane of its ``k_floor`` nearest cells
   (fitted again to those on or under the first fit's median, so roofs and crowns do not tilt
   it) gives the floor, the ``floor_quantile`` of their residuals; the point scores
   (floor - r) / ``below`` (:func:`floor_scores`). A piece that is real but cut off (ground seen
   under a roof, through a crown) lies at the level of the lowest surface around and stays.
3. **Pits** (low). A return lower than every other return within ``pit_radius`` metres (at
   least 4 x the horizontal point spacing, so sparse clouds have neighbours enough) by more than
   ``below`` metres: a lone multipath return under the ground, of any cloud density
   (:func:`pit_scores`, the extended local minimum of Chen et al. 2012 with one return per
   pit).

The score is the largest of the three (NaN where no test applied); a point is flagged above 1.
Thresholds are metres that hold for any survey: nothing real lies ``below`` (1 m) under the
lowest surface around it. Tuned on the Zurich (LAStools) and laspy append-bug tiles of
``shared/data/airborne``; the other five airborne tiles and the seven ISPRS samples were only
used to check. Not in the paper (Leslar, Wang & Hu 2010); pure numpy/scipy.

Chen, Z., Devereux, B., Gao, B., Amable, G. (2012). Upward-fusion urban DTM generating method
using airborne lidar data. ISPRS J. Photogramm. Remote Sens. 72, 121-130 (extended local
minimum).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from algorithms.checks import check_xyz
from algorithms.params import Parameters, param
from algorithms.result import DetectorResult


@dataclass(frozen=True)
class DetachedParameters(Parameters):
    """Airborne: returns detached from the surface, in small clusters over or under it, in
    pieces under the lowest surface, or alone in a pit."""

    link: float = param(
        3.0, "Metres: points closer than max(link, link_spacing x median spacing) form one "
        "cluster.", gt=0, le=1000)
    link_spacing: float = param(
        4.0, "Multiple of the cloud's median nearest-neighbour distance for the link.",
        ge=0, le=1000)
    max_cluster: int = param(10, "Clusters of at most this many points are tested.",
                             ge=1, le=1000)
    k_surface: int = param(128, "Surface points (nearest in XY) for the local plane.",
                           ge=3, le=2000)
    below: float = param(1.0, "Metres under the lowest surface around: outlier.",
                         gt=0, le=1000)
    above: float = param(10.0, "Metres over the highest surface residual: outlier.",
                         gt=0, le=1000)
    piece_points: int = param(
        1000, "Pieces of fewer points (joined through occupied voxels) are compared with the "
        "lowest surface; 0 turns that test off.", ge=0, le=1_000_000)
    k_floor: int = param(64, "Cells of the lowest surface (nearest in XY) for the floor plane.",
                         ge=3, le=2000)
    floor_quantile: float = param(
        0.05, "Quantile of the lowest-surface cells' residuals taken as the floor.", ge=0, le=0.5)
    pit_radius: float = param(
        3.0, "Metres (at least 4 x the point spacing): a return lower than every other return "
        "this close is a pit; 0 turns that test off.", ge=0, le=1000)

_BATCH = 20_000  # candidate points per batch of plane fits (bounds memory to ~100 MB)


def small_clusters(xyz: np.ndarray, link: float, max_cluster: int) -> np.ndarray:
    """Points whose link-graph component has at most ``max_cluster`` points.

    xyz : (n, 3) float64 metres. Two points are linked when their distance is <= ``link``.
    Returns (n,) bool.

    Exactness of the k-nearest-neighbour shortcut: a component C with |C| <= max_cluster is a
    union of components of the kNN-within-link graph (its edges are a subset). Conversely, if
    a kNN component D has |D| <= max_cluster, every point of D has fewer than max_cluster
    other points within ``link`` (otherwise all max_cluster of them would be in D, making
    |D| > max_cluster), so all its link neighbours are among its kNN and in D: D is a link
    component. Hence the small components of both graphs are the same.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    n = len(xyz)
    if n == 0:
        return np.zeros(0, dtype=bool)
    k = min(max_cluster + 1, n)  # the point itself plus max_cluster others
    dist, idx = cKDTree(xyz).query(xyz, k=k, distance_upper_bound=link)
    dist = dist.reshape(n, k)
    idx = idx.reshape(n, k)
    ok = np.isfinite(dist)
    rows = np.repeat(np.arange(n), k)[ok.ravel()]
    graph = coo_matrix((np.ones(rows.size, dtype=np.int8), (rows, idx[ok])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    size = np.bincount(label)
    return size[label] <= max_cluster


def envelope_scores(
    xyz: np.ndarray,
    candidate: np.ndarray,
    *,
    k_surface: int = 128,
    below: float = 1.0,
    above: float = 2.0,
) -> np.ndarray:
    """Score of each candidate against the plane of its ``k_surface`` nearest surface points.

    xyz : (n, 3) float64 metres; candidate : (n,) bool (the others are the surface points).
    Returns (n,) float64: max((lowest - r) / below, (r - highest) / above) for candidates, where
    r is the candidate's residual from the least-squares plane of the surface points nearest in
    XY and lowest/highest are those surface points' own residuals; NaN for non-candidates and
    when fewer than 3 surface points exist.
    """
    score = np.full(len(xyz), np.nan)
    cand = np.flatnonzero(candidate)
    surf = np.flatnonzero(~candidate)
    if cand.size == 0 or surf.size < 3:
        return score
    from scipy.spatial import cKDTree

    k = min(k_surface, surf.size)
    tree = cKDTree(xyz[surf, :2])
    for start in range(0, cand.size, _BATCH):
        ci = cand[start:start + _BATCH]
        _, j = tree.query(xyz[ci, :2], k=k)
        r, res_nb = _plane_residuals(xyz[surf[j.reshape(len(ci), k)]], xyz[ci])
        score[ci] = np.maximum((res_nb.min(axis=1) - r) / below, (r - res_nb.max(axis=1)) / above)
    return score


def _plane_residuals(
    nb: np.ndarray, points: np.ndarray, lower_refit: bool = False, slope: bool = False
) -> tuple[np.ndarray, ...]:
    """Residuals from the least-squares plane z = a + b x + c y of each neighbourhood.

    nb : (m, k, 3) neighbourhoods; points : (m, 3), one tested point per neighbourhood.
    Returns (r, res): (m,) residual of each point and (m, k) residuals of its neighbours;
    with ``slope`` also (m,) the plane's gradient sqrt(b^2 + c^2).
    ``lower_refit`` fits each plane again to the neighbours on or under the first plane's
    median residual (the lower surface; roofs and crowns over it do not tilt it).
    """
    centre = nb.mean(axis=1, keepdims=True)  # centring keeps 5e6 m coordinates exact
    q = nb - centre
    design = np.concatenate([q[:, :, :2], np.ones(q.shape[:2] + (1,))], axis=2)
    weight = np.ones(q.shape[:2])
    for _ in range(2 if lower_refit else 1):
        wd = design * weight[..., None]
        normal = np.einsum("mki,mkj->mij", wd, design)
        # A tiny ridge keeps collinear neighbourhoods (a single scan line) solvable.
        scale = np.maximum(np.trace(normal, axis1=1, axis2=2), 1.0)[:, None, None]
        normal += 1e-9 * scale * np.eye(3)
        rhs = np.einsum("mki,mk->mi", wd, q[:, :, 2])
        coef = np.linalg.solve(normal, rhs[..., None])[..., 0]  # (m, 3): b, c, a
        res = q[:, :, 2] - np.einsum("mki,mi->mk", design, coef)
        weight = (res <= np.median(res, axis=1, keepdims=True)).astype(np.float64)
    p = points - centre[:, 0]
    r = p[:, 2] - (p[:, 0] * coef[:, 0] + p[:, 1] * coef[:, 1] + coef[:, 2])
    if slope:
        return r, res, np.hypot(coef[:, 0], coef[:, 1])
    return r, res


def median_spacing(xyz: np.ndarray, max_points: int = 100_000) -> float:
    """Median distance of a point to its nearest other point (a regular subsample of at most
    ``max_points`` query points, all points in the tree). xyz : (n, 3). 0.0 for n < 2."""
    if len(xyz) < 2:
        return 0.0
    from scipy.spatial import cKDTree

    step = max(1, len(xyz) // max_points)
    dist, _ = cKDTree(xyz).query(xyz[::step], k=2)
    return float(np.median(dist[:, 1]))


def xy_spacing(xyz: np.ndarray, k: int = 8, max_points: int = 100_000) -> float:
    """Horizontal spacing of a cloud: sqrt(pi / k) x the median XY distance to the k-th nearest
    other point (1 / sqrt(density) for points spread over a surface; a regular subsample of at
    most ``max_points`` query points). xyz : (n, 3). 0.0 for n <= k."""
    if len(xyz) <= k:
        return 0.0
    from scipy.spatial import cKDTree

    step = max(1, len(xyz) // max_points)
    dist, _ = cKDTree(xyz[:, :2]).query(xyz[::step, :2], k=k + 1)
    return float(np.median(dist[:, k]) * np.sqrt(np.pi / k))


#: The 13 voxel offsets that, with their opposites, make a voxel's 26 neighbours.
_FORWARD = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)
                     if (i, j, k) > (0, 0, 0)])


def voxel_pieces(xyz: np.ndarray, size: float) -> np.ndarray:
    """Pieces of a cloud: points joined through occupied voxels that share a face, an edge or
    a corner (26-connectivity). Points closer than ``size`` always share a piece; points more
    than 2 sqrt(3) ``size`` apart are joined only through others.

    xyz : (n, 3) metres; size : voxel edge in metres. Returns (n,) int piece labels 0..p-1.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = len(xyz)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    ijk = np.floor((xyz - xyz.min(axis=0)) / size).astype(np.int64) + 1
    dims = ijk.max(axis=0) + 2
    key = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]
    voxels, inverse = np.unique(key, return_inverse=True)
    m = voxels.size
    rows, cols = [], []
    for di, dj, dk in _FORWARD:
        wanted = voxels + (di * dims[1] + dj) * dims[2] + dk
        pos = np.minimum(np.searchsorted(voxels, wanted), m - 1)
        hit = voxels[pos] == wanted
        rows.append(np.flatnonzero(hit))
        cols.append(pos[hit])
    r, c = np.concatenate(rows), np.concatenate(cols)
    graph = coo_matrix((np.ones(r.size, dtype=np.int8), (r, c)), shape=(m, m))
    _, label = connected_components(graph, directed=False)
    return label[inverse.ravel()]


#: Share of the points allowed in small pieces at the scale :func:`surface_scale` chooses.
SMALL_PIECE_SHARE = 0.01
#: Above this share, small pieces are still the surface falling apart (no plateau yet).
PLATEAU_MAX_SHARE = 0.10
#: A share that keeps more than this part of itself at the next size has reached its plateau.
PLATEAU_RATIO = 0.8
#: Voxel sizes tried by :func:`surface_scale`: 0.1 m x sqrt(2)^i up to this many metres.
LARGEST_VOXEL = 16.0


def surface_scale(
    xyz: np.ndarray, piece_points: int, start: float = 0.0
) -> tuple[float | None, np.ndarray]:
    """The finest voxel size at which the real surfaces of a cloud are whole.

    Sizes 0.1 m x sqrt(2)^i from ``start`` up to ``LARGEST_VOXEL`` are tried; the share of
    points in pieces (:func:`voxel_pieces`) of fewer than ``piece_points`` points falls as the
    surfaces join, then stays flat while only detached clumps (and real patches cut off by data
    gaps) remain small. The size chosen is the first where that share is at most
    ``SMALL_PIECE_SHARE``, or at most ``PLATEAU_MAX_SHARE`` and still more than
    ``PLATEAU_RATIO`` of itself at the next size.

    Returns (size, small): the size (None when none qualifies) and the (n,) bool mask of the
    points in small pieces at that size (all False for None).
    """
    n = len(xyz)
    size = 0.1
    while size < start:
        size *= np.sqrt(2.0)

    def small_at(s: float) -> np.ndarray:
        label = voxel_pieces(xyz, s)
        counts = np.bincount(label)
        return counts[label] < piece_points

    small = small_at(size)
    while size <= LARGEST_VOXEL * 1.0001:
        share = np.count_nonzero(small) / max(n, 1)
        if share <= SMALL_PIECE_SHARE:
            return float(size), small
        bigger = small_at(size * np.sqrt(2.0))
        if share <= PLATEAU_MAX_SHARE and np.count_nonzero(bigger) > PLATEAU_RATIO * share * n:
            return float(size), small
        size, small = size * np.sqrt(2.0), bigger
    return None, np.zeros(n, dtype=bool)


def lowest_per_cell(xyz: np.ndarray, index: np.ndarray, cell: float) -> np.ndarray:
    """Indices (into xyz) of the lowest point of ``xyz[index]`` in each occupied XY cell of
    ``cell`` metres."""
    if index.size == 0:
        return index
    ij = np.floor((xyz[index, :2] - xyz[index, :2].min(axis=0)) / cell).astype(np.int64)
    key = ij[:, 0] * (ij[:, 1].max() + 1) + ij[:, 1]
    order = np.lexsort((xyz[index, 2], key))
    first = np.r_[True, key[order][1:] != key[order][:-1]]
    return index[order[first]]


def floor_scores(
    xyz: np.ndarray,
    candidate: np.ndarray,
    reference: np.ndarray,
    *,
    k_floor: int = 64,
    quantile: float = 0.05,
    below: float = 1.0,
    reach: float = np.inf,
    max_slope: float = np.inf,
) -> np.ndarray:
    """How far each candidate lies under the lowest surface around it, in units of ``below``.

    xyz : (n, 3) metres; candidate : (n,) bool; reference : indices of points sampling the
    lowest surface (one per cell, :func:`lowest_per_cell`). For each candidate, the plane of
    its ``k_floor`` nearest reference points in XY, fitted again to those on or under the first
    fit's median residual, gives residuals; the floor is their ``quantile``.
    Returns (n,) float64: (floor - r) / below for candidates within ``reach`` metres (XY) of a
    reference point, where r is the candidate's residual; NaN elsewhere. Where the floor
    plane's gradient exceeds ``max_slope`` (no floor: e.g. a facade's lowest returns) the
    candidate is compared with the lowest of those reference points instead: (lowest z - z) /
    below.
    """
    score = np.full(len(xyz), np.nan)
    cand = np.flatnonzero(candidate)
    if cand.size == 0 or reference.size < 3:
        return score
    from scipy.spatial import cKDTree

    k = min(k_floor, reference.size)
    tree = cKDTree(xyz[reference, :2])
    for start in range(0, cand.size, _BATCH):
        ci = cand[start:start + _BATCH]
        dist, j = tree.query(xyz[ci, :2], k=k)
        dist, j = dist.reshape(len(ci), k), j.reshape(len(ci), k)
        r, res, grad = _plane_residuals(xyz[reference[j]], xyz[ci], lower_refit=True,
                                        slope=True)
        floor = np.quantile(res, quantile, axis=1)
        lowest = xyz[reference[j], 2].min(axis=1)
        under = np.where(grad <= max_slope, floor - r, lowest - xyz[ci, 2])
        score[ci] = np.where(dist[:, 0] <= reach, under / below, np.nan)
    return score


def pit_scores(
    xyz: np.ndarray, radius: float, *, below: float = 1.0, min_points: int = 8
) -> np.ndarray:
    """How far the lowest return of each cell lies under every other return around it.

    xyz : (n, 3) metres. Cells are ``radius`` / 3 wide; the lowest return of a cell is compared
    with the lowest other return of the 7 x 7 cells around it (about ``radius`` metres each
    way) when they hold at least ``min_points`` others. Returns (n,) float64:
    (lowest other z - z) / below for those returns, NaN for all others.
    """
    n = len(xyz)
    score = np.full(n, np.nan)
    if n < 2 or radius <= 0:
        return score
    reach = 3
    ij = np.floor((xyz[:, :2] - xyz[:, :2].min(axis=0)) / (radius / reach)).astype(np.int64)
    ij += reach + 1
    width = ij[:, 1].max() + reach + 2
    key = ij[:, 0] * width + ij[:, 1]
    order = np.lexsort((xyz[:, 2], key))
    sorted_key = key[order]
    first = np.flatnonzero(np.r_[True, sorted_key[1:] != sorted_key[:-1]])
    cells = sorted_key[first]
    count = np.diff(np.r_[first, n])
    lowest = xyz[order[first], 2]
    second = np.where(count > 1, xyz[order[np.minimum(first + 1, n - 1)], 2], np.inf)
    others, around = second, count - 1
    m = cells.size
    for di in range(-reach, reach + 1):
        for dj in range(-reach, reach + 1):
            if di == 0 and dj == 0:
                continue
            wanted = cells + di * width + dj
            pos = np.minimum(np.searchsorted(cells, wanted), m - 1)
            hit = cells[pos] == wanted
            others[hit] = np.minimum(others[hit], lowest[pos[hit]])
            around[hit] += count[pos[hit]]
    ok = around >= min_points
    score[order[first[ok]]] = (others[ok] - lowest[ok]) / below
    return score


def detect_detached(
    xyz: np.ndarray,
    *,
    link: float = 3.0,
    link_spacing: float = 4.0,
    max_cluster: int = 10,
    k_surface: int = 128,
    below: float = 1.0,
    above: float = 10.0,
    piece_points: int = 1000,
    k_floor: int = 64,
    floor_quantile: float = 0.05,
    pit_radius: float = 3.0,
) -> DetectorResult:
    """Flag returns detached from the surface: the three tests of the module docstring.

    xyz : (n, 3) float64 metres (any frame; the arithmetic is centred).
    Returns a DetectorResult: score = the largest score of the tests that applied to the point
    (:func:`envelope_scores`, :func:`floor_scores`, :func:`pit_scores`), NaN where none did;
    critical value 1. ``info`` reports the link, voxel size and radius used and what each test
    tested and flagged.

    >>> rng = np.random.default_rng(0)
    >>> ground = np.c_[rng.uniform(0, 30, (3000, 2)), rng.normal(0, 0.02, 3000)]
    >>> pts = np.vstack([ground, [[15.0, 15.0, 30.0], [15.5, 15.0, -5.0]]])
    >>> np.flatnonzero(detect_detached(pts).flagged).tolist()
    [3000, 3001]
    """
    DetachedParameters(link=link, link_spacing=link_spacing, max_cluster=max_cluster,
                       k_surface=k_surface, below=below, above=above, piece_points=piece_points,
                       k_floor=k_floor, floor_quantile=floor_quantile, pit_radius=pit_radius)
    xyz = check_xyz(xyz)
    local = xyz - xyz.mean(axis=0) if len(xyz) else xyz
    spacing = median_spacing(local)
    link_used = max(float(link), link_spacing * spacing)
    candidate = small_clusters(local, link_used, max_cluster)
    cluster = envelope_scores(local, candidate, k_surface=k_surface, below=below, above=above)

    horizontal = xy_spacing(local)
    piece = np.full(len(xyz), np.nan)
    voxel = None
    if piece_points > 0 and len(xyz) > piece_points:
        voxel, small = surface_scale(local, piece_points, start=horizontal)
        if voxel is not None and small.any():
            reference = lowest_per_cell(local, np.flatnonzero(~small), 2 * voxel)
            piece = floor_scores(local, small, reference, k_floor=k_floor,
                                 quantile=floor_quantile, below=below, reach=4 * voxel)
    radius = max(float(pit_radius), 4 * horizontal) if pit_radius > 0 else 0.0
    pit = pit_scores(local, radius, below=below) if radius > 0 else np.full(len(xyz), np.nan)

    score = np.fmax(np.fmax(cluster, piece), pit)
    flagged = np.nan_to_num(score, nan=0.0) > 1.0

    def found(s: np.ndarray) -> dict[str, int]:
        return {"points_tested": int(np.isfinite(s).sum()),
                "points_flagged": int((np.nan_to_num(s, nan=0.0) > 1.0).sum())}

    info = {
        "link": float(link), "link_spacing": float(link_spacing),
        "median_spacing": spacing, "link_used": link_used,
        "max_cluster": int(max_cluster), "k_surface": int(k_surface),
        "below": float(below), "above": float(above),
        "candidates": int(candidate.sum()),
        "xy_spacing": horizontal,
        "clusters": found(cluster),
        "pieces": {"voxel": voxel, "piece_points": int(piece_points), **found(piece)},
        "pits": {"radius": radius, **found(pit)},
        "points_tested": int(np.isfinite(score).sum()), "points_flagged": int(flagged.sum()),
    }
    return DetectorResult(score=score, flagged=flagged, critical_value=1.0, info=info)
