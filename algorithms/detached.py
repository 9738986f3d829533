"""Gross outliers of airborne clouds: small clusters detached from the local surface.

Airborne gross errors (multipath returns tens of metres below the ground, birds and cloud
returns far above it) arrive in small clumps: on the laspy append-bug tile 385 of the 387 gross
points form clumps of one or two points when points closer than 1 m are linked, and they hide
each other from any per-point neighbourhood test (their nearest neighbour is a fellow outlier).
This detector therefore works on clusters, in two steps:

1. Candidates: the connected components of the graph that links points closer than
   max(``link``, ``link_spacing`` x the cloud's median nearest-neighbour distance) metres (so
   sparse clouds, 1-2 m spacing, are not cut into fragments); a component of at most
   ``max_cluster`` points is a candidate cluster. The
   components are computed exactly from each point's ``max_cluster`` nearest neighbours (a
   component that small is fully linked through them; see :func:`small_clusters`).
2. Test: for each candidate point, the ``k_surface`` nearest NON-candidate points in XY get a
   least-squares plane z = a + b x + c y (centred; the local slope of steep terrain is taken
   out); the candidate is an outlier when its plane residual lies more than ``below`` metres
   under the lowest residual of those surface points, or more than ``above`` metres over the
   highest one. Score = max((lowest - r) / below, (r - highest) / above); flagged when > 1.
   ``above`` is large (10 m) because real objects (trees, buildings) that are sparse enough to
   form small clusters stand a few metres over the ground's envelope; gross high returns stand
   tens of metres over it. ``below`` is small: nothing real lies under the ground.

Small real objects inside the surface's vertical envelope (a lone pole, a sparse hedge, a
scan line at a tile's edge) stay unflagged; the envelope is the surface's own range of
heights, so no sigma is guessed. Not in the paper (Leslar, Wang & Hu 2010); pure numpy/scipy.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from algorithms.checks import check_xyz
from algorithms.params import Parameters, param
from algorithms.result import DetectorResult


@dataclass(frozen=True)
class DetachedParameters(Parameters):
    """Airborne: small clusters lying under or over the local surface's height envelope."""

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
    below: float = param(1.0, "Metres under the lowest surface residual: outlier.",
                         gt=0, le=1000)
    above: float = param(10.0, "Metres over the highest surface residual: outlier.",
                         gt=0, le=1000)

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
        nb = xyz[surf[j.reshape(len(ci), k)]]  # (m, k, 3)
        centre = nb.mean(axis=1, keepdims=True)  # centring keeps 5e6 m coordinates exact
        q = nb - centre
        design = np.concatenate([q[:, :, :2], np.ones(q.shape[:2] + (1,))], axis=2)
        normal = np.einsum("mki,mkj->mij", design, design)
        # A tiny ridge keeps collinear neighbourhoods (a single scan line) solvable.
        scale = np.maximum(np.trace(normal, axis1=1, axis2=2), 1.0)[:, None, None]
        normal += 1e-9 * scale * np.eye(3)
        rhs = np.einsum("mki,mk->mi", design, q[:, :, 2])
        coef = np.linalg.solve(normal, rhs[..., None])[..., 0]  # (m, 3): b, c, a
        res_nb = q[:, :, 2] - np.einsum("mki,mi->mk", design, coef)
        p = xyz[ci] - centre[:, 0]
        r = p[:, 2] - (p[:, 0] * coef[:, 0] + p[:, 1] * coef[:, 1] + coef[:, 2])
        score[ci] = np.maximum((res_nb.min(axis=1) - r) / below, (r - res_nb.max(axis=1)) / above)
    return score


def median_spacing(xyz: np.ndarray, max_points: int = 100_000) -> float:
    """Median distance of a point to its nearest other point (a regular subsample of at most
    ``max_points`` query points, all points in the tree). xyz : (n, 3). 0.0 for n < 2."""
    if len(xyz) < 2:
        return 0.0
    from scipy.spatial import cKDTree

    step = max(1, len(xyz) // max_points)
    dist, _ = cKDTree(xyz).query(xyz[::step], k=2)
    return float(np.median(dist[:, 1]))


def detect_detached(
    xyz: np.ndarray,
    *,
    link: float = 3.0,
    link_spacing: float = 4.0,
    max_cluster: int = 10,
    k_surface: int = 128,
    below: float = 1.0,
    above: float = 10.0,
) -> DetectorResult:
    """Flag small clusters that lie under or over the local surface's vertical envelope.

    xyz : (n, 3) float64 metres (any frame; centre large coordinates first for speed of the
    tree, the arithmetic itself is centred per neighbourhood).
    The link distance is max(link, link_spacing x :func:`median_spacing`); info reports it.
    Returns a DetectorResult: score of :func:`envelope_scores` for the points of small clusters,
    NaN for the others (not tested); critical value 1.

    >>> rng = np.random.default_rng(0)
    >>> ground = np.c_[rng.uniform(0, 30, (3000, 2)), rng.normal(0, 0.02, 3000)]
    >>> pts = np.vstack([ground, [[15.0, 15.0, 30.0], [15.5, 15.0, -5.0]]])
    >>> np.flatnonzero(detect_detached(pts).flagged).tolist()
    [3000, 3001]
    """
    DetachedParameters(link=link, link_spacing=link_spacing, max_cluster=max_cluster,
                       k_surface=k_surface, below=below, above=above)
    xyz = check_xyz(xyz)
    local = xyz - xyz.mean(axis=0) if len(xyz) else xyz
    spacing = median_spacing(local)
    link_used = max(float(link), link_spacing * spacing)
    candidate = small_clusters(local, link_used, max_cluster)
    score = envelope_scores(local, candidate, k_surface=k_surface, below=below, above=above)
    flagged = np.nan_to_num(score, nan=0.0) > 1.0
    info = {
        "link": float(link), "link_spacing": float(link_spacing),
        "median_spacing": spacing, "link_used": link_used,
        "max_cluster": int(max_cluster), "k_surface": int(k_surface),
        "below": float(below), "above": float(above),
        "candidates": int(candidate.sum()),
        "points_tested": int(np.isfinite(score).sum()), "points_flagged": int(flagged.sum()),
    }
    return DetectorResult(score=score, flagged=flagged, critical_value=1.0, info=info)
