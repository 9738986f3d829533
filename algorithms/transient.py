"""The ``transient`` detector: structure seen at one moment only, attached to nothing.

The paper counts moving objects as outliers. A moving barrier arm is a clean cylinder, so no
surface test can flag it, and the beams that saw through its place at other times often went to
the sky (no return) or left the clipped strip, so ``free_space`` has no evidence either. What
remains is time: a static surface is seen again, by the other scanner or on another pass, so
next to its points lie points recorded at other moments; a moving object's place is occupied at
one moment only.

For n points with coordinates and GPS times:

1. a point is *persistent* when among its ``k`` nearest neighbours, within ``radius``, there is
   one recorded at least ``min_dt`` seconds earlier or later;
2. the other points are *single-epoch* (a moving object, or a static surface that only one
   scanner saw once, e.g. a car's end face or a wall behind a parked car);
3. single-epoch points are joined into clusters (links of at most ``radius``); a cluster that
   touches a persistent point (within ``radius``, among the k nearest) is part of the static
   scene, occluded elsewhere; a cluster attached to nothing floats;
4. a floating cluster is flagged only where its place was seen at another moment, else being
   seen once says nothing about motion (one scanner on one pass sees every static surface once,
   and a surface hidden from the other scanner is seen once too). Both must hold:

   - *the scene beside it was seen again*: of the returns the same scanner fired just before
     and just after the cluster's returns (its neighbours along the scan line, by GPS time),
     at least half are persistent;
   - *the place under or over it was seen again*: at least half of its points have a
     persistent point within ``radius`` in plan (the road under a moving car was seen by the
     other scanner or pass; nobody sees the ground under a parked car's roof).

Score per point: 0 persistent, 1 single-epoch in an attached or unrevisited cluster, 2
single-epoch in a floating, revisited cluster (flagged; critical value 1.5). Pure numpy/scipy
(cKDTree, sparse connected components).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from algorithms.errors import ParameterError
from algorithms.params import Parameters, param
from algorithms.result import DetectorResult


@dataclass(frozen=True)
class TransientParameters(Parameters):
    """Mobile mapping: single-epoch clusters attached to nothing (moving objects); with a
    trajectory also points that other beams saw through (free-space evidence)."""

    k: int = param(24, "Neighbours searched per point.", ge=1, le=200)
    radius: float = param(
        0.2, "Metres: neighbours this close count; clusters link at this distance.",
        gt=0, le=100)
    min_dt: float = param(
        0.5, "Seconds: a neighbour recorded this much earlier or later makes a point "
        "persistent (seen again by the other scanner or on another pass).", gt=0, le=1e6)
    free_space_radius: float = param(
        0.006, "With a trajectory file: metres a beam must pass within a point to see through "
        "it (free-space evidence).", gt=0, le=10)
    free_space_margin: float = param(
        0.08, "With a trajectory file: metres a beam must end beyond a point to count (the "
        "least: more where the beam meets the surface at its end at a grazing angle).",
        ge=0, le=100)
    free_space_min_rays: int = param(
        1, "With a trajectory file: beams that saw through a point to flag it.", ge=1, le=1000)
    lever_arms: tuple[tuple[int, float, float, float], ...] = param(
        (),
        "With a trajectory file: [point_source_id, forward, left, up] metres of each scanner "
        "from the trajectory's reference point in the vehicle frame (heading from the "
        "trajectory's motion), as the system's calibration gives them. A scanner not listed is "
        "placed from its own points (a profile scanner's beams turn at one rate in one plane "
        "through it); one that cannot be placed gives no free-space evidence.")

#: Points per kNN batch.
KNN_BATCH = 262_144


def neighbour_table(xyz: np.ndarray, k: int, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """(n, k) int64 indices of each point's k nearest other points and (n, k) bool "within
    radius" (False also for the padding of clouds with fewer than k + 1 points)."""
    from scipy.spatial import cKDTree

    n = len(xyz)
    kk = min(k + 1, n)
    tree = cKDTree(xyz)
    idx = np.zeros((n, k), dtype=np.int64)
    near = np.zeros((n, k), dtype=bool)
    for s in range(0, n, KNN_BATCH):
        d, j = tree.query(xyz[s:s + KNN_BATCH], k=kk, workers=-1)
        d, j = d.reshape(-1, kk), j.reshape(-1, kk)
        rows = np.arange(s, s + len(j))
        # drop each point itself (not necessarily column 0 when points coincide)
        not_self = j != rows[:, None]
        keep = np.cumsum(not_self, axis=1) <= k
        sel = not_self & keep
        # the selected columns first, in distance order (stable sort of "not selected")
        cols = np.argsort(~sel, axis=1, kind="stable")[:, :k]
        width = cols.shape[1]
        idx[s:s + len(j), :width] = np.take_along_axis(j, cols, axis=1)
        near[s:s + len(j), :width] = (np.take_along_axis(d, cols, axis=1) <= radius) & (
            np.take_along_axis(sel, cols, axis=1))
    return idx, near


def persistent_points(gps_time: np.ndarray, idx: np.ndarray, near: np.ndarray,
                      min_dt: float) -> np.ndarray:
    """(n,) bool: a neighbour within radius was recorded at least min_dt seconds apart."""
    dt = np.abs(gps_time[idx] - gps_time[:, None])
    return np.any(near & (dt >= min_dt), axis=1)


def scan_line_neighbours(gps_time: np.ndarray, source: np.ndarray | None
                         ) -> tuple[np.ndarray, np.ndarray]:
    """(n,) int64 index of the return the same scanner fired just before and just after each
    one (-1 at a scanner's first and last return); source None: one scanner."""
    n = len(gps_time)
    src = np.zeros(n, dtype=np.int64) if source is None else np.asarray(source, dtype=np.int64)
    order = np.lexsort((gps_time, src))
    before = np.full(n, -1, dtype=np.int64)
    after = np.full(n, -1, dtype=np.int64)
    same = src[order[1:]] == src[order[:-1]]
    before[order[1:][same]] = order[:-1][same]
    after[order[:-1][same]] = order[1:][same]
    return before, after


def cluster_labels(xyz: np.ndarray, single: np.ndarray, radius: float) -> tuple[int, np.ndarray]:
    """Number of clusters and the cluster of each of the points ``single`` (links <= radius)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    pairs = cKDTree(xyz[single]).query_pairs(radius, output_type="ndarray")
    m = single.size
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(m, m))
    return connected_components(graph, directed=False)


def revisited_clusters(xyz: np.ndarray, persistent: np.ndarray, single: np.ndarray,
                       label: np.ndarray, n_comp: int, neighbours: tuple[np.ndarray, np.ndarray],
                       radius: float) -> np.ndarray:
    """(n_comp,) bool: the cluster's place was seen at another moment (step 4 of the module
    docstring): at least half of its scan-line neighbours outside it are persistent, and at
    least half of its points have a persistent point within ``radius`` in plan."""
    from scipy.spatial import cKDTree

    n = len(xyz)
    cluster = np.full(n, -1, dtype=np.int64)
    cluster[single] = label
    flanks = np.zeros(n_comp)
    seen_flanks = np.zeros(n_comp)
    for nb in neighbours:
        j = nb[single]
        outside = (j >= 0) & (cluster[np.maximum(j, 0)] != label)
        np.add.at(flanks, label[outside], 1.0)
        np.add.at(seen_flanks, label[outside], persistent[j[outside]])
    beside = (flanks > 0) & (2.0 * seen_flanks >= flanks)
    seen = np.flatnonzero(persistent)
    if seen.size == 0:
        return np.zeros(n_comp, dtype=bool)
    covered = cKDTree(xyz[seen, :2]).query_ball_point(
        xyz[single, :2], radius, return_length=True) > 0
    size = np.bincount(label, minlength=n_comp)
    under = 2.0 * np.bincount(label, weights=covered, minlength=n_comp) >= size
    return beside & under


def floating_clusters(xyz: np.ndarray, persistent: np.ndarray, idx: np.ndarray,
                      near: np.ndarray, radius: float,
                      neighbours: tuple[np.ndarray, np.ndarray] | None = None
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Two (n,) bool: single-epoch points whose cluster (links <= radius) touches no persistent
    point among the neighbour table (floating), and those of them whose place was seen at
    another moment (:func:`revisited_clusters`, with the scan-line ``neighbours`` of
    :func:`scan_line_neighbours`; None: every floating cluster counts as revisited)."""
    single = np.flatnonzero(~persistent)
    floating = np.zeros(len(xyz), dtype=bool)
    flagged = np.zeros(len(xyz), dtype=bool)
    if single.size == 0:
        return floating, flagged
    touches = np.any(near[single] & persistent[idx[single]], axis=1)
    n_comp, label = cluster_labels(xyz, single, radius)
    attached = np.zeros(n_comp, dtype=bool)
    attached[label[touches]] = True
    floating[single[~attached[label]]] = True
    if neighbours is None:
        return floating, floating.copy()
    revisited = revisited_clusters(xyz, persistent, single, label, n_comp, neighbours, radius)
    flagged[single[~attached[label] & revisited[label]]] = True
    return floating, flagged


def detect_transient(
    xyz: np.ndarray,
    gps_time: np.ndarray,
    source: np.ndarray | None = None,
    *,
    k: int = 24,
    radius: float = 0.2,
    min_dt: float = 0.5,
) -> DetectorResult:
    """Flag floating single-epoch clusters (module docstring).

    xyz (n, 3) metres, gps_time (n,) seconds (finite), source (n,) the scanner of each return
    (point_source_id; None: one scanner). Returns a DetectorResult with score (n,) in {0, 1,
    2}, flagged = score == 2, critical_value 1.5.
    """
    arr = np.asarray(xyz, dtype=np.float64)
    t = np.asarray(gps_time, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3 or t.shape != (len(arr),):
        raise ParameterError(f"xyz must have shape (n, 3) and gps_time (n,), got {arr.shape} "
                             f"and {t.shape}")
    if not (np.all(np.isfinite(arr)) and np.all(np.isfinite(t))):
        raise ParameterError("xyz or gps_time holds NaN or infinite values")
    if source is not None and np.shape(source) != (len(arr),):
        raise ParameterError(f"source must have shape ({len(arr)},), got {np.shape(source)}")
    TransientParameters(k=k, radius=radius, min_dt=min_dt)
    n = len(arr)
    info = {"k": int(k), "radius": float(radius), "min_dt": float(min_dt), "points": n}
    if n < 2:
        score = np.zeros(n)
        info.update(points_tested=n, points_flagged=0, single_epoch=n, floating_not_revisited=0)
        return DetectorResult(score, np.zeros(n, bool), 1.5, info)
    local = arr - arr.mean(axis=0)
    idx, near = neighbour_table(local, k, radius)
    persistent = persistent_points(t - t.min(), idx, near, min_dt)
    floating, flagged = floating_clusters(local, persistent, idx, near, radius,
                                          scan_line_neighbours(t, source))
    score = np.where(persistent, 0.0, np.where(flagged, 2.0, 1.0))
    info.update(points_tested=n, points_flagged=int(flagged.sum()),
                single_epoch=int((~persistent).sum()),
                floating_not_revisited=int((floating & ~flagged).sum()))
    return DetectorResult(score=score, flagged=flagged, critical_value=1.5, info=info)
