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

Tile by tile (the notes before :func:`pending_estimate`): the median spacing, the horizontal
spacing and the voxel size are whole-cloud quantities, measured from values every point has from
its neighbourhood alone (the spacings' subsample is every m-th point in file order, which a tiled
run reproduces from the points' values gathered in file order); every grid (voxels, floor and pit
cells) starts at a corner given by the caller, the file's lower-left corner in the pipeline,
rather than at the points' own lowest corner, so a tile puts each point in the whole cloud's
cells (this shifts the grids of a whole-cloud run by less than a cell: on the airborne tiles the
pieces test flags a few returns more or fewer). Equal distances at the k-th neighbour are broken
by position (:func:`nearest_first`), so a tile picks the whole cloud's neighbours.

Chen, Z., Devereux, B., Gao, B., Amable, G. (2012). Upward-fusion urban DTM generating method
using airborne lidar data. ISPRS J. Photogramm. Remote Sens. 72, 121-130 (extended local
minimum).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from algorithms.cells import cell_keys, forward_offsets, offset_keys
from algorithms.checks import check_xyz
from algorithms.columns import column_min
from algorithms.params import Parameters, param
from algorithms.result import DetectorResult
from algorithms.stats import strided_sample
from algorithms.threads import worker_threads


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
    spacing: float | Literal["auto"] = param(
        "auto", "Metres: the cloud's median nearest-neighbour distance, or 'auto' to measure "
        "it (reported in the statistics).", ge=0, le=1000)
    spacing_xy: float | Literal["auto"] = param(
        "auto", "Metres: the cloud's horizontal point spacing, or 'auto' to measure it "
        "(reported in the statistics).", ge=0, le=1000)
    voxel: float | Literal["auto"] = param(
        "auto", "Metres: the voxel size the cloud is cut into pieces at, or 'auto' for the "
        "finest at which the surfaces are whole (reported); 0 turns the pieces test off.",
        ge=0, le=1000)

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
    label = cluster_labels(xyz, link, max_cluster)
    return np.bincount(label)[label] <= max_cluster if len(xyz) else np.zeros(0, dtype=bool)


def cluster_labels(xyz: np.ndarray, link: float, max_cluster: int) -> np.ndarray:
    """(n,) component labels of the graph linking each point to its ``max_cluster`` nearest
    neighbours within ``link`` (:func:`small_clusters`: its small components are the link
    graph's)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    from algorithms.neighbours import neighbour_tree, query_nearest

    n = len(xyz)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    k = min(max_cluster + 1, n)  # the point itself plus max_cluster others
    dist, idx = query_nearest(neighbour_tree(xyz), xyz, k, distance_upper_bound=link)
    dist = dist.reshape(n, k)
    idx = idx.reshape(n, k)
    ok = np.isfinite(dist)
    rows = np.repeat(np.arange(n), k)[ok.ravel()]
    graph = coo_matrix((np.ones(rows.size, dtype=np.int8), (rows, idx[ok])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    return label


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
        _, j = nearest_first(tree, xyz[ci, :2], k)
        r, res_nb = _plane_residuals(xyz[surf[j.reshape(len(ci), k)]], xyz[ci])
        score[ci] = np.maximum((res_nb.min(axis=1) - r) / below, (r - res_nb.max(axis=1)) / above)
    return score


#: Neighbours past the k-th looked at to break ties in distance by position.
TIE_SLACK = 8


def nearest_first(tree: Any, queries: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """(m, k) distances and indices of each query's k nearest points of a cKDTree, equal
    distances in the order of the tree's points (the first in the cloud first): a tile, whose
    points are the cloud's in the same order, then picks the same neighbours as the whole
    cloud where several lie at the k-th distance (a millimetre grid makes that common).
    Ties reaching past ``TIE_SLACK`` further neighbours keep the tree's order.

    One neighbour past the k-th tells which queries have a tie across the k-th distance; only
    those are asked for the slack (in dense clouds most have none)."""
    from algorithms.neighbours import by_distance_then_index, query_nearest

    m = len(queries)
    kk = min(k + 1, tree.n)
    dist, idx = query_nearest(tree, queries, kk)
    dist, idx = dist.reshape(m, kk), idx.reshape(m, kk).astype(np.int64, copy=False)
    if kk > k:
        tied = np.flatnonzero(dist[:, k] == dist[:, k - 1])
        dist, idx = dist[:, :k], idx[:, :k]  # views: a copy of the answers costs fresh pages
        if tied.size:
            wide = min(k + TIE_SLACK, tree.n)
            d, i = tree.query(queries[tied], k=wide, workers=worker_threads())
            d, i = d.reshape(tied.size, wide), i.reshape(tied.size, wide).astype(np.int64)
            by_distance_then_index(d, i)
            dist[tied], idx[tied] = d[:, :k], i[:, :k]
    by_distance_then_index(dist, idx)
    return dist, idx


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
    ``max_points`` query points, all points in the tree). xyz : (n, 3). 0.0 for n < 2.

    The subsample is every ``n // max_points``-th point in array order, so a run tile by tile
    gets the same median from every point's :func:`nearest_distance` in file order
    (:func:`strided_median`)."""
    if len(xyz) < 2:
        return 0.0
    from scipy.spatial import cKDTree

    step = max(1, len(xyz) // max_points)
    dist, _ = cKDTree(xyz).query(xyz[::step], k=2)
    return float(np.median(dist[:, 1]))


def xy_spacing(xyz: np.ndarray, k: int = 8, max_points: int = 100_000) -> float:
    """Horizontal spacing of a cloud: sqrt(pi / k) x the median XY distance to the k-th nearest
    other point (1 / sqrt(density) for points spread over a surface; a regular subsample of at
    most ``max_points`` query points, as :func:`median_spacing`). xyz : (n, 3). 0.0 for
    n <= k."""
    if len(xyz) <= k:
        return 0.0
    from scipy.spatial import cKDTree

    step = max(1, len(xyz) // max_points)
    dist, _ = cKDTree(xyz[:, :2]).query(xyz[::step, :2], k=k + 1)
    return float(np.median(dist[:, k]) * np.sqrt(np.pi / k))


#: Neighbours of :func:`xy_spacing`.
XY_SPACING_K = 8
#: Query points of :func:`median_spacing` and :func:`xy_spacing`.
SPACING_SAMPLE = 100_000


def nearest_distance(xyz: np.ndarray, wanted: np.ndarray | None = None) -> np.ndarray:
    """(n,) each point's distance to its nearest other point (inf without one): what
    :func:`median_spacing` takes the median of; NaN outside the mask ``wanted`` when given."""
    return _kth_or_nan(xyz, 2, wanted)


def xy_kth_distance(xyz: np.ndarray, k: int = XY_SPACING_K,
                    wanted: np.ndarray | None = None) -> np.ndarray:
    """(n,) each point's XY distance to its k-th nearest other point (inf without one): what
    :func:`xy_spacing` takes the median of; NaN outside the mask ``wanted`` when given."""
    return _kth_or_nan(xyz[:, :2], k + 1, wanted)


def _kth_or_nan(points: np.ndarray, k: int, wanted: np.ndarray | None) -> np.ndarray:
    """(n,) :func:`algorithms.tiles.kth_distance_within` (itself counted first) for the points
    of ``wanted`` (default all), NaN for the others."""
    from algorithms.tiles import kth_distance_within

    if wanted is None:
        wanted = np.ones(len(points), dtype=bool)
    return np.where(wanted, kth_distance_within(points, k, wanted), np.nan)


def strided_median(parts: Iterable[np.ndarray], max_points: int = SPACING_SAMPLE) -> float:
    """The median of every ``max(1, m // max_points)``-th finite value of ``parts`` (consecutive
    pieces of one array, m finite values in all), first included; NaN for m = 0. With the
    values of :func:`nearest_distance` of all n points (n >= 2) it is :func:`median_spacing`;
    of :func:`xy_kth_distance`, over sqrt(pi / k), :func:`xy_spacing`."""
    sample = strided_sample(parts, max_points)
    return float(np.median(sample)) if sample.size else float("nan")


def xy_spacing_of_values(parts: Iterable[np.ndarray]) -> float:
    """:func:`xy_spacing` from the points' :func:`xy_kth_distance` values given in file order
    as ``parts`` (NaN: not measured): sqrt(pi / k) x their :func:`strided_median`; 0.0 without
    any (at most k points)."""
    value = strided_median(parts) * float(np.sqrt(np.pi / XY_SPACING_K))
    return value if np.isfinite(value) else 0.0


def grid_index(coords: np.ndarray, size: float, origin: np.ndarray) -> np.ndarray:
    """(n, d) int64 index of each point's cell of ``size`` metres in the grid whose corner is
    ``origin`` (d = 2: XY cells, 3: voxels): one formula, so two runs with the same origin
    put the same point in the same cell."""
    d = len(origin)
    return np.floor((coords[:, :d] - origin) / size).astype(np.int64)


def voxel_pieces(xyz: np.ndarray, size: float, origin: np.ndarray | None = None) -> np.ndarray:
    """Pieces of a cloud: points joined through occupied voxels that share a face, an edge or
    a corner (26-connectivity). Points closer than ``size`` always share a piece; points more
    than 2 sqrt(3) ``size`` apart are joined only through others.

    xyz : (n, 3) metres; size : voxel edge in metres; origin : (3,) a corner of the voxel grid
    (default: the lowest coordinates; a run tile by tile shares one with the whole cloud's).
    Returns (n,) int piece labels 0..p-1.
    """
    n = len(xyz)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    ijk = grid_index(xyz, size, column_min(xyz) if origin is None else origin)
    voxels, inverse = distinct_voxels(ijk)
    return voxel_components(voxels)[inverse]


def distinct_voxels(ijk: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct rows (m, 3) of the voxel indices ``ijk`` (n, 3) int, in order, and the row
    of each (n,): ``np.unique(ijk, axis=0, return_inverse=True)`` by one int64 key a voxel."""
    keys, inverse = np.unique(cell_keys(ijk, reach=0)[0], return_inverse=True)
    inverse = inverse.ravel()
    voxels = np.empty((len(keys), 3), dtype=np.int64)
    voxels[inverse] = ijk  # every point of a voxel writes the same indices
    return voxels, inverse


def voxel_components(voxels: np.ndarray) -> np.ndarray:
    """(m,) piece label of each of the distinct voxels ``voxels`` (m, 3) int (grid indices):
    the connected components of the voxels that share a face, an edge or a corner."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    m = len(voxels)
    if m == 0:
        return np.zeros(0, dtype=np.int64)
    key, strides = cell_keys(voxels, reach=1)
    order = np.argsort(key)
    key = key[order]
    rows, cols = [], []
    for step in offset_keys(forward_offsets(1), strides):
        wanted = key + step
        pos = np.minimum(np.searchsorted(key, wanted), m - 1)
        hit = key[pos] == wanted
        rows.append(order[hit])
        cols.append(order[pos[hit]])
    r, c = np.concatenate(rows), np.concatenate(cols)
    graph = coo_matrix((np.ones(r.size, dtype=np.int8), (r, c)), shape=(m, m))
    return connected_components(graph, directed=False)[1].astype(np.int64)


#: Share of the points allowed in small pieces at the scale :func:`surface_scale` chooses.
SMALL_PIECE_SHARE = 0.01
#: Above this share, small pieces are still the surface falling apart (no plateau yet).
PLATEAU_MAX_SHARE = 0.10
#: A share that keeps more than this part of itself at the next size has reached its plateau.
PLATEAU_RATIO = 0.8
#: Voxel sizes tried by :func:`surface_scale`: 0.1 m x sqrt(2)^i up to this many metres.
LARGEST_VOXEL = 16.0


def voxel_ladder(start: float = 0.0) -> list[float]:
    """The voxel sizes :func:`surface_scale` may look at: 0.1 m x sqrt(2)^i from the first at
    least ``start``, up to the first beyond ``LARGEST_VOXEL`` (whose share decides whether the
    last size is a plateau). Every other size is exactly twice the one two steps before
    (0.1 x 2^j and 0.1 sqrt(2) x 2^j): a voxel of one is eight of the other's, which lets
    :func:`ladder_pieces` cut each family's grids from the finest one."""
    def size(i: int) -> float:
        return (0.1 if i % 2 == 0 else 0.1 * np.sqrt(2.0)) * 2.0 ** (i // 2)

    i = 0
    while size(i) < start:
        i += 1
    sizes = [size(i)]
    while sizes[-1] <= LARGEST_VOXEL * 1.0001:
        i += 1
        sizes.append(size(i))
    return [float(v) for v in sizes]


def choose_scale(small_counts: list[int], n: int) -> int | None:
    """Index into the ladder of the size :func:`surface_scale` chooses from the number of points
    in small pieces at each size (at least up to the decision), None when none qualifies."""
    for i, count in enumerate(small_counts[:-1]):
        share = count / max(n, 1)
        if share <= SMALL_PIECE_SHARE:
            return i
        if share <= PLATEAU_MAX_SHARE and small_counts[i + 1] > PLATEAU_RATIO * share * n:
            return i
    return None


def small_pieces(xyz: np.ndarray, size: float, piece_points: int,
                 origin: np.ndarray | None = None) -> np.ndarray:
    """(n,) bool: the points in pieces (:func:`voxel_pieces`) of fewer than ``piece_points``."""
    label = voxel_pieces(xyz, size, origin)
    return np.bincount(label)[label] < piece_points if len(xyz) else np.zeros(0, bool)


def surface_scale(
    xyz: np.ndarray, piece_points: int, start: float = 0.0, origin: np.ndarray | None = None,
) -> tuple[float | None, np.ndarray]:
    """The finest voxel size at which the real surfaces of a cloud are whole.

    Sizes 0.1 m x sqrt(2)^i from ``start`` up to ``LARGEST_VOXEL`` are tried
    (:func:`voxel_ladder`); the share of points in pieces (:func:`voxel_pieces`, grid corner
    ``origin``) of fewer than ``piece_points`` points falls as the surfaces join, then stays
    flat while only detached clumps (and real patches cut off by data gaps) remain small. The
    size chosen is the first where that share is at most ``SMALL_PIECE_SHARE``, or at most
    ``PLATEAU_MAX_SHARE`` and still more than ``PLATEAU_RATIO`` of itself at the next size
    (:func:`choose_scale`: a run tile by tile chooses from every point's
    :func:`small_ladder`).

    Returns (size, small): the size (None when none qualifies) and the (n,) bool mask of the
    points in small pieces at that size (all False for None).
    """
    n = len(xyz)
    sizes = voxel_ladder(start)
    masks: list[np.ndarray | None] = [small_pieces(xyz, sizes[0], piece_points, origin)]
    counts = [int(np.count_nonzero(masks[0]))]
    for size in sizes[1:]:
        masks.append(small_pieces(xyz, size, piece_points, origin))
        counts.append(int(np.count_nonzero(masks[-1])))
        chosen = choose_scale(counts, n)
        if chosen is not None:
            mask = masks[chosen]
            assert mask is not None
            return sizes[chosen], mask
        masks[-2] = None  # decided against: only the latest is still needed
    return None, np.zeros(n, dtype=bool)


def small_ladder(xyz: np.ndarray, piece_points: int, start: float = 0.0,
                 origin: np.ndarray | None = None) -> np.ndarray:
    """(n,) float: bit i set where the point lies in a small piece at ``voxel_ladder(start)[i]``
    (at most 18 bits: exact in a float). Summed over a cloud's points, the counts
    :func:`surface_scale` chooses from (:func:`scale_of_ladder`)."""
    local = xyz - (column_min(xyz) if origin is None else origin) if len(xyz) else xyz
    return ladder_pieces(local, piece_points, start)[0]


def ladder_pieces(local: np.ndarray, piece_points: int,
                  start: float) -> tuple[np.ndarray, np.ndarray]:
    """(bits, reach), each (n,): :func:`small_ladder`'s bits of ``local`` (grids at 0) and the
    largest :func:`piece_reach` over the ladder.

    The same pieces as :func:`voxel_pieces` at each size of :func:`voxel_ladder`, cut on the
    voxels rather than the points: a voxel of size 2s is the eight of size s whose indices
    halve to its own (floor(floor(x / s) / 2) = floor(x / 2s), and 2s is exact in floating
    point), so only the finest grid of each of the ladder's two families reads the points.
    Each voxel carries its points' count and XY bounds up the family.
    """
    n = len(local)
    bits = np.zeros(n, dtype=np.int64)
    reach = np.zeros(n)
    if n == 0:
        return bits.astype(np.float64), reach
    sizes = voxel_ladder(start)
    for first in (0, 1):
        family = sizes[first::2]
        if not family:  # a ladder of one size (a start beyond the last but one)
            continue
        voxels, point_voxel, stats = _finest_voxels(local, family[0])
        for j, size in enumerate(family):
            if j:
                voxels, up, stats = _coarser_voxels(voxels, stats)
                point_voxel = up[point_voxel]
            small, extent = _small_voxel_pieces(voxels, stats, piece_points)
            at_point = small[point_voxel]
            bits |= at_point.astype(np.int64) << (first + 2 * j)
            if at_point.any():
                reach[at_point] = np.maximum(reach[at_point],
                                             extent[point_voxel[at_point]] + 3 * size)
    return bits.astype(np.float64), reach


def _finest_voxels(local: np.ndarray, size: float
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The distinct voxels (m, 3) of ``size`` (grid at 0) of the points ``local``, each point's
    voxel (n,) and each voxel's [points, x min, y min, x max, y max] (m, 5)."""
    ijk = grid_index(local, size, np.zeros(3))
    voxels, inverse = distinct_voxels(ijk)
    stats = np.empty((len(voxels), 5))
    stats[:, 0] = np.bincount(inverse, minlength=len(voxels))
    stats[:, 1:] = _xy_bounds(inverse, len(voxels), local[:, 0], local[:, 1], local[:, 0],
                              local[:, 1])
    return voxels, inverse, stats


def _coarser_voxels(voxels: np.ndarray, stats: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The voxels twice as large (indices halved), each finer voxel's coarser one and the
    coarser voxels' counts and XY bounds."""
    coarse, up = distinct_voxels(np.floor_divide(voxels, 2))
    return coarse, up, _grouped_stats(stats, up, len(coarse))


def _grouped_stats(stats: np.ndarray, group: np.ndarray, groups: int) -> np.ndarray:
    """[points, x min, y min, x max, y max] of each group of rows of ``stats``."""
    out = np.empty((groups, 5))
    out[:, 0] = np.bincount(group, weights=stats[:, 0], minlength=groups)
    out[:, 1:] = _xy_bounds(group, groups, *stats[:, 1:].T)
    return out


def _xy_bounds(group: np.ndarray, groups: int, x_low: np.ndarray, y_low: np.ndarray,
               x_high: np.ndarray, y_high: np.ndarray) -> np.ndarray:
    """(groups, 4) [x min, y min, x max, y max] of each group of rows: the least of the
    ``_low`` values and the largest of the ``_high`` ones (+-inf for an empty group). One
    contiguous column at a time: ``np.minimum.at`` then takes numpy's fast path (about 30
    times faster than on the strided columns of a 2-D array)."""
    out = np.empty((4, groups))
    out[:2], out[2:] = np.inf, -np.inf
    for row, values, reduce in ((0, x_low, np.minimum), (1, y_low, np.minimum),
                                (2, x_high, np.maximum), (3, y_high, np.maximum)):
        reduce.at(out[row], group, np.ascontiguousarray(values))
    return out.T


def _small_voxel_pieces(voxels: np.ndarray, stats: np.ndarray, piece_points: int
                        ) -> tuple[np.ndarray, np.ndarray]:
    """(m,) bool: the voxel lies in a piece of fewer than ``piece_points`` points; (m,) the
    XY diagonal of its piece's points (NaN where the piece is not small)."""
    label = voxel_components(voxels)
    pieces = int(label.max()) + 1
    points = np.bincount(label, weights=stats[:, 0], minlength=pieces)
    small = points[label] < piece_points
    extent = np.full(len(voxels), np.nan)
    if small.any():
        rows = np.flatnonzero(small)
        bounds = _grouped_stats(stats[rows], label[rows], pieces)
        diagonal = np.hypot(bounds[:, 3] - bounds[:, 1], bounds[:, 4] - bounds[:, 2])
        extent[rows] = diagonal[label[rows]]
    return small, extent


def scale_of_ladder(parts: Iterable[np.ndarray], piece_points: int, start: float,
                    cut_from: float | None = None) -> float:
    """The size :func:`surface_scale` chooses for the cloud whose points' :func:`small_ladder`
    values are ``parts`` (NaN: not in the cloud); 0.0 where it chooses none or the cloud has at
    most ``piece_points`` points (as :func:`detect_detached` leaves the test out).

    ``cut_from``: the start the values' ladder was cut from, when not ``start`` (``cut_from``
    <= ``start`` <= ``LARGEST_VOXEL``): the ladder from ``start`` is a suffix of that one, so
    each value's bits are shifted by the sizes before ``start``."""
    sizes = voxel_ladder(start)
    shift = 0
    if cut_from is not None:
        if not cut_from <= start <= LARGEST_VOXEL:
            raise ValueError(f"a ladder cut from {cut_from} holds no ladder from {start}")
        shift = len(voxel_ladder(cut_from)) - len(sizes)
    counts = np.zeros(len(sizes), dtype=np.int64)
    n = 0
    for part in parts:
        v = np.asarray(part)
        bits = v[np.isfinite(v)].astype(np.int64) >> shift
        n += bits.size
        for i in range(len(sizes)):
            counts[i] += int(np.count_nonzero((bits >> i) & 1))
    if piece_points <= 0 or n <= piece_points:
        return 0.0
    chosen = choose_scale(counts.tolist(), n)
    return 0.0 if chosen is None else sizes[chosen]


def lowest_per_cell(xyz: np.ndarray, index: np.ndarray, cell: float,
                    origin: np.ndarray | None = None) -> np.ndarray:
    """Indices (into xyz) of the lowest point of ``xyz[index]`` in each occupied XY cell of
    ``cell`` metres (grid corner ``origin`` (2,), default the lowest XY of ``xyz[index]``)."""
    if index.size == 0:
        return index
    ij = grid_index(xyz[index], cell, column_min(xyz[index, :2]) if origin is None else origin)
    ij -= column_min(ij)
    key = ij[:, 0] * (ij[:, 1].max() + 1) + ij[:, 1]
    return index[first_lowest_per_key(key, xyz[index, 2])]


def first_lowest_per_key(key: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Positions of the lowest of ``z`` (n,) among each distinct ``key`` (n,) int, the first
    in order where several are lowest, in increasing key order: the first of each key in
    ``np.lexsort((z, key))``. A minimum per key and one pass over the points that reach it,
    about 2.7 times faster than sorting (n,) pairs."""
    keys, group = np.unique(key, return_inverse=True)
    group = group.ravel()
    floor = np.full(len(keys), np.inf)
    np.minimum.at(floor, group, z)
    at_floor = np.flatnonzero(z == floor[group])
    _, first = np.unique(group[at_floor], return_index=True)
    return at_floor[first]


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
        dist, j = nearest_first(tree, xyz[ci, :2], k)
        r, res, grad = _plane_residuals(xyz[reference[j]], xyz[ci], lower_refit=True,
                                        slope=True)
        floor = np.quantile(res, quantile, axis=1)
        lowest = xyz[reference[j], 2].min(axis=1)
        under = np.where(grad <= max_slope, floor - r, lowest - xyz[ci, 2])
        score[ci] = np.where(dist[:, 0] <= reach, under / below, np.nan)
    return score


def pit_scores(
    xyz: np.ndarray, radius: float, *, below: float = 1.0, min_points: int = 8,
    origin: np.ndarray | None = None,
) -> np.ndarray:
    """How far the lowest return of each cell lies under every other return around it.

    xyz : (n, 3) metres. Cells are ``radius`` / 3 wide; the lowest return of a cell is compared
    with the lowest other return of the 7 x 7 cells around it (about ``radius`` metres each
    way) when they hold at least ``min_points`` others; the cells' grid starts at ``origin``
    (2,) (default: the lowest XY). Returns (n,) float64:
    (lowest other z - z) / below for those returns, NaN for all others.
    """
    n = len(xyz)
    score = np.full(n, np.nan)
    if n < 2 or radius <= 0:
        return score
    reach = 3
    ij = grid_index(xyz, radius / reach, column_min(xyz[:, :2]) if origin is None else origin)
    ij += reach + 1 - column_min(ij)
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
    spacing: float | str = "auto",
    spacing_xy: float | str = "auto",
    voxel: float | str = "auto",
    origin: np.ndarray | None = None,
) -> DetectorResult:
    """Flag returns detached from the surface: the three tests of the module docstring.

    xyz : (n, 3) float64 metres (any frame; the arithmetic is relative to ``origin``).
    ``spacing``, ``spacing_xy``, ``voxel``: the cloud's median nearest-neighbour distance,
    horizontal spacing and voxel size, "auto" to measure them here (:func:`median_spacing`,
    :func:`xy_spacing`, :func:`surface_scale`); a run tile by tile measures them over the whole
    cloud first and gives them. ``origin`` : (3,) the corner of every grid (voxels, floor and
    pit cells; default the lowest coordinates): runs that share it put a point in the same
    cells.
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
                       k_floor=k_floor, floor_quantile=floor_quantile, pit_radius=pit_radius,
                       spacing=spacing, spacing_xy=spacing_xy, voxel=voxel)
    xyz = check_xyz(xyz)
    local = relative(xyz, origin)
    spacing_used = median_spacing(local) if spacing == "auto" else float(spacing)
    link_used = max(float(link), link_spacing * spacing_used)
    candidate = small_clusters(local, link_used, max_cluster)
    cluster = envelope_scores(local, candidate, k_surface=k_surface, below=below, above=above)

    horizontal = xy_spacing(local) if spacing_xy == "auto" else float(spacing_xy)
    piece = np.full(len(xyz), np.nan)
    voxel_used = voxel_size(local, piece_points, horizontal, voxel)
    if voxel_used is not None:
        small = small_pieces(local, voxel_used, piece_points, np.zeros(3))
        if small.any():
            reference = lowest_per_cell(local, np.flatnonzero(~small), 2 * voxel_used,
                                        np.zeros(2))
            piece = floor_scores(local, small, reference, k_floor=k_floor,
                                 quantile=floor_quantile, below=below, reach=4 * voxel_used)
    radius = pit_radius_used(pit_radius, horizontal)
    pit = (pit_scores(local, radius, below=below, origin=np.zeros(2)) if radius > 0
           else np.full(len(xyz), np.nan))

    score = np.fmax(np.fmax(cluster, piece), pit)
    flagged = np.nan_to_num(score, nan=0.0) > 1.0

    def found(s: np.ndarray) -> dict[str, int]:
        return {"points_tested": int(np.isfinite(s).sum()),
                "points_flagged": int((np.nan_to_num(s, nan=0.0) > 1.0).sum())}

    info = {
        "link": float(link), "link_spacing": float(link_spacing),
        "median_spacing": spacing_used, "link_used": link_used,
        "max_cluster": int(max_cluster), "k_surface": int(k_surface),
        "below": float(below), "above": float(above),
        "candidates": int(candidate.sum()),
        "xy_spacing": horizontal,
        "clusters": found(cluster),
        "pieces": {"voxel": voxel_used, "piece_points": int(piece_points), **found(piece)},
        "pits": {"radius": radius, **found(pit)},
        "points_tested": int(np.isfinite(score).sum()), "points_flagged": int(flagged.sum()),
    }
    return DetectorResult(score=score, flagged=flagged, critical_value=1.0, info=info)


def relative(xyz: np.ndarray, origin: np.ndarray | None) -> np.ndarray:
    """``xyz`` minus ``origin`` (default its lowest coordinates): the frame every grid of
    :func:`detect_detached` starts at 0 in."""
    if origin is None:
        return xyz - column_min(xyz) if len(xyz) else xyz.copy()
    return xyz - np.asarray(origin, dtype=np.float64)


def voxel_size(local: np.ndarray, piece_points: int, horizontal: float,
               voxel: float | str) -> float | None:
    """The voxel size of the pieces test (None: the test is off): measured with "auto"
    (:func:`surface_scale`, grid corner at 0), else the given one (0: off)."""
    if voxel != "auto":
        return float(voxel) if float(voxel) > 0 else None
    if piece_points <= 0 or len(local) <= piece_points:
        return None
    return surface_scale(local, piece_points, start=horizontal, origin=np.zeros(3))[0]


def pit_radius_used(pit_radius: float, horizontal: float) -> float:
    """The pits test's radius: ``pit_radius``, at least 4 x the horizontal spacing (0: off)."""
    return max(float(pit_radius), 4 * horizontal) if pit_radius > 0 else 0.0


# --------------------------------------------------------------------------- tile by tile
#
# A run tile by tile (a region of the cloud: a tile and the points around it) gives the whole
# cloud's result for a point when everything the point's result depends on lies in the region.
# Each quantity below comes with the XY metres around a point it depended on in the region, so
# that any point outside the region that could change it is nearer than that: a result whose
# reach is at most the distance from the point to the region's edge is the whole cloud's.
#
# - Small clusters: a component found small in the region is the whole cloud's unless a
#   member has a link neighbour outside the region (reach: the component's XY extent + link);
#   a component found large is large in the whole cloud (the region's graph is part of it).
# - Pieces at a voxel size: the same with the 26 voxels around a member (reach: the piece's
#   extent + 3 voxels, more than the 2 sqrt(2) voxels XY a neighbour voxel spans).
# - Envelope of a candidate: its k_surface nearest surface points in XY, exact when every
#   point as near has its cluster exact. Floor of a point in a small piece: its k_floor
#   nearest lowest-cell points, exact when every cell that near (its points lie within the
#   k_floor-th distance + a cell's diagonal) has its points and their pieces exact.
# - Pits: the 7 x 7 cells around the point's cell, 4 sqrt(2) cells away at most.

#: The estimates a run tile by tile makes over the whole cloud first, in order.
ESTIMATES = ("spacing", "spacing_xy", "voxel")


def pending_estimate(params: DetachedParameters) -> str | None:
    """The first of :data:`ESTIMATES` still "auto" (the voxel only where the pieces test is
    on), None when all are given."""
    for name in ESTIMATES:
        if getattr(params, name) == "auto" and (name != "voxel" or params.piece_points > 0):
            return name
    return None


def estimate_values(xyz: np.ndarray, params: DetachedParameters,
                    origin: np.ndarray | None, wanted: np.ndarray | None = None) -> np.ndarray:
    """(n,) each point's value for the pending estimate (:func:`nearest_distance`,
    :func:`xy_kth_distance`, :func:`small_ladder`), from its neighbourhood alone; the first
    two only for the points of the mask ``wanted`` when given (NaN elsewhere)."""
    local = relative(check_xyz(xyz), origin)
    name = pending_estimate(params)
    if name == "spacing":
        return nearest_distance(local, wanted)
    if name == "spacing_xy":
        return xy_kth_distance(local, wanted=wanted)
    if name == "voxel":
        return ladder_pieces(local, params.piece_points, float(params.spacing_xy))[0]
    raise ValueError("every estimate of these parameters is given")


def pin_estimate(params: DetachedParameters,
                 parts: list[np.ndarray]) -> tuple[DetachedParameters, dict[str, float]]:
    """The parameters with the pending estimate fixed from every point's value (``parts``: in
    file order), as the whole cloud's run measures it, and the statistics' note on it."""
    from dataclasses import replace

    name = pending_estimate(params)
    if name == "spacing":
        value = strided_median(parts)
        value = value if np.isfinite(value) else 0.0  # fewer than 2 points
        return replace(params, spacing=value), {"median_spacing": value}
    if name == "spacing_xy":
        value = xy_spacing_of_values(parts)
        return replace(params, spacing_xy=value), {"xy_spacing": value}
    if name == "voxel":
        value = scale_of_ladder(parts, params.piece_points, float(params.spacing_xy))
        return replace(params, voxel=value), {}
    raise ValueError("every estimate of these parameters is given")


def tile_reach(xyz: np.ndarray, params: DetachedParameters, where: np.ndarray,
               origin: np.ndarray | None, allowed: np.ndarray | None = None) -> np.ndarray:
    """(n,) XY metres around each point of the mask ``where`` (others: 0) its result depended
    on in this cloud (a region of a larger one: see above); with an estimate pending, that of
    its value (:func:`estimate_values`). ``allowed``: as for
    :func:`algorithms.height_field.tile_reach`."""
    from algorithms.tiles import kth_distance_within

    local = relative(check_xyz(xyz), origin)
    out = np.zeros(len(local))
    if not where.any():
        return out
    name = pending_estimate(params)
    if name == "spacing":
        out = kth_distance_within(local, 2, where, allowed)
    elif name == "spacing_xy":
        out = kth_distance_within(local[:, :2], XY_SPACING_K + 1, where, allowed)
    elif name == "voxel":
        out = ladder_pieces(local, params.piece_points, float(params.spacing_xy))[1]
    else:
        out = _result_reach(local, params, where)
    return np.where(where, out, 0.0)


def piece_reach(local: np.ndarray, size: float, piece_points: int) -> np.ndarray:
    """(n,) 0 for points in pieces of at least ``piece_points`` points (large in any larger
    cloud), the piece's XY extent + 3 voxels for the others."""
    label = voxel_pieces(local, size, np.zeros(3)) if len(local) else np.zeros(0, np.int64)
    small = np.bincount(label)[label] < piece_points if len(local) else np.zeros(0, bool)
    return np.where(small, label_extent(local[:, :2], label) + 3 * size, 0.0)


def label_extent(xy: np.ndarray, label: np.ndarray) -> np.ndarray:
    """(n,) the diagonal of the XY bounding box of each point's label: no two points of a
    label are further apart."""
    if len(xy) == 0:
        return np.zeros(0)
    order = np.argsort(label, kind="stable")
    sorted_label = label[order]
    starts = np.flatnonzero(np.r_[True, sorted_label[1:] != sorted_label[:-1]])
    lo = np.minimum.reduceat(xy[order], starts, axis=0)
    hi = np.maximum.reduceat(xy[order], starts, axis=0)
    extent = np.hypot(*(hi - lo).T)
    out = np.empty(len(xy))
    out[order] = np.repeat(extent, np.diff(np.r_[starts, len(xy)]))
    return out


def _result_reach(local: np.ndarray, params: DetachedParameters,
                  where: np.ndarray) -> np.ndarray:
    """The reach of :func:`detect_detached`'s result with every estimate given."""
    from scipy.spatial import cKDTree

    p = params
    link_used = max(float(p.link), p.link_spacing * float(p.spacing))
    label = cluster_labels(local, link_used, p.max_cluster)
    candidate = np.bincount(label)[label] <= p.max_cluster
    out = np.where(candidate, label_extent(local[:, :2], label) + link_used, 0.0)
    cand = np.flatnonzero(candidate & where)
    if cand.size:
        surf = np.flatnonzero(~candidate)
        if surf.size < p.k_surface:
            out[cand] = np.inf  # a larger cloud may hold more surface points
        else:
            dist, _ = cKDTree(local[surf, :2]).query(local[cand, :2], k=[p.k_surface])
            out[cand] = np.maximum(out[cand], reach_through(local, cand, dist[:, 0], out))
    voxel = voxel_size(local, p.piece_points, float(p.spacing_xy), p.voxel)
    if voxel is not None:
        around = piece_reach(local, voxel, p.piece_points)
        out = np.maximum(out, around)
        small = np.flatnonzero((around > 0) & where)
        if small.size:
            reference = lowest_per_cell(local, np.flatnonzero(around == 0), 2 * voxel,
                                        np.zeros(2))
            if reference.size < p.k_floor:
                out[small] = np.inf
            else:
                dist, _ = cKDTree(local[reference, :2]).query(local[small, :2], k=[p.k_floor])
                cells = dist[:, 0] + 3 * voxel  # a cell 2 voxels wide: diagonal 2 sqrt(2)
                out[small] = np.maximum(out[small], reach_through(local, small, cells, around))
    radius = pit_radius_used(p.pit_radius, float(p.spacing_xy))
    if radius > 0:
        out = np.maximum(out, 4 * np.sqrt(2.0) * radius / 3 * 1.001)
    return out


def reach_through(local: np.ndarray, points: np.ndarray, radius: np.ndarray,
                   reach: np.ndarray) -> np.ndarray:
    """(m,) for each of ``points``, the largest of ``radius`` and |q - p| + reach(q) over the
    points q within ``radius`` (XY) whose own reach is not 0: what depending on everything
    that near reaches. (A hair further than ``radius`` counts too: a bound, never less.)"""
    from scipy.spatial import cKDTree

    from algorithms.neighbours import ball_candidates

    out = radius.astype(np.float64).copy()
    uncertain = np.flatnonzero(reach > 0)
    if uncertain.size == 0 or points.size == 0:
        return out
    xy = local[:, :2]
    row, near = ball_candidates(cKDTree(xy[uncertain]), xy, points, radius)
    q = uncertain[near]
    np.maximum.at(out, row, np.hypot(*(xy[q] - xy[points[row]]).T) + reach[q])
    return out
