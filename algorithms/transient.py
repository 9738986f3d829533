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
   scene, occluded elsewhere; a cluster attached to nothing floats: it is flagged.

Score per point: 0 persistent, 1 single-epoch in an attached cluster, 2 single-epoch in a
floating cluster (flagged; critical value 1.5). Pure numpy/scipy (cKDTree, sparse connected
components).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from algorithms.errors import ParameterError
from algorithms.params import Parameters, param
from algorithms.result import DetectorResult

#: The simulator's two scanners: [point_source_id, forward, left, up] metres from the
#: trajectory's reference point.
SIMULATOR_LEVER_ARMS = ((1, -0.6, 0.45, 0.0), (2, -0.6, -0.45, 0.0))


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
        0.08, "With a trajectory file: metres a beam must end beyond a point to count.",
        ge=0, le=100)
    free_space_min_rays: int = param(
        1, "With a trajectory file: beams that saw through a point to flag it.", ge=1, le=1000)
    lever_arms: tuple[tuple[int, float, float, float], ...] = param(
        SIMULATOR_LEVER_ARMS,
        "With a trajectory file: [point_source_id, forward, left, up] metres of each scanner "
        "from the trajectory's reference point in the vehicle frame (heading from the "
        "trajectory's motion). Default: the simulator's two scanners (trajectory = roof point "
        "at scanner height). Scanners not listed sit at the reference point.")

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


def floating_clusters(xyz: np.ndarray, persistent: np.ndarray, idx: np.ndarray,
                      near: np.ndarray, radius: float) -> np.ndarray:
    """(n,) bool: single-epoch points whose cluster (links <= radius) touches no persistent
    point among the neighbour table."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    single = np.flatnonzero(~persistent)
    out = np.zeros(len(xyz), dtype=bool)
    if single.size == 0:
        return out
    touches = np.any(near[single] & persistent[idx[single]], axis=1)
    pairs = cKDTree(xyz[single]).query_pairs(radius, output_type="ndarray")
    m = single.size
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(m, m))
    n_comp, label = connected_components(graph, directed=False)
    attached = np.zeros(n_comp, dtype=bool)
    attached[label[touches]] = True
    out[single[~attached[label]]] = True
    return out


def transient_reach(
    xyz: np.ndarray, gps_time: np.ndarray, *, k: int = 24, radius: float = 0.2,
    min_dt: float = 0.5,
) -> np.ndarray:
    """(n,) metres around each point that its score depends on.

    A persistent point's score depends on the points within ``radius``. A single-epoch point's
    depends on its whole cluster: on the points within ``radius`` of every member (are they
    single-epoch, do they link the cluster on) and within ``radius`` of those (are they
    persistent), so its reach is the cluster's extent (its bounding box's diagonal, an upper
    bound of any member's distance) plus twice ``radius``.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    arr = np.asarray(xyz, dtype=np.float64)
    n = len(arr)
    reach = np.full(n, float(radius))
    if n < 2:
        return reach
    local = arr - arr.mean(axis=0)
    t = np.asarray(gps_time, dtype=np.float64)
    idx, near = neighbour_table(local, k, radius)
    single = np.flatnonzero(~persistent_points(t - t.min(), idx, near, min_dt))
    if single.size == 0:
        return reach
    pairs = cKDTree(local[single]).query_pairs(radius, output_type="ndarray")
    m = single.size
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(m, m))
    n_comp, label = connected_components(graph, directed=False)
    lo = np.full((n_comp, 3), np.inf)
    hi = np.full((n_comp, 3), -np.inf)
    np.minimum.at(lo, label, local[single])
    np.maximum.at(hi, label, local[single])
    extent = np.linalg.norm(hi - lo, axis=1)
    reach[single] = extent[label] + 2.0 * radius
    return reach


def detect_transient(
    xyz: np.ndarray,
    gps_time: np.ndarray,
    *,
    k: int = 24,
    radius: float = 0.2,
    min_dt: float = 0.5,
) -> DetectorResult:
    """Flag floating single-epoch clusters (module docstring).

    xyz (n, 3) metres, gps_time (n,) seconds (finite). Returns a DetectorResult with score (n,)
    in {0, 1, 2}, flagged = score == 2, critical_value 1.5.
    """
    arr = np.asarray(xyz, dtype=np.float64)
    t = np.asarray(gps_time, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3 or t.shape != (len(arr),):
        raise ParameterError(f"xyz must have shape (n, 3) and gps_time (n,), got {arr.shape} "
                             f"and {t.shape}")
    if not (np.all(np.isfinite(arr)) and np.all(np.isfinite(t))):
        raise ParameterError("xyz or gps_time holds NaN or infinite values")
    TransientParameters(k=k, radius=radius, min_dt=min_dt)
    n = len(arr)
    info = {"k": int(k), "radius": float(radius), "min_dt": float(min_dt), "points": n}
    if n < 2:
        score = np.zeros(n)
        info.update(points_tested=n, points_flagged=0, single_epoch=n)
        return DetectorResult(score, np.zeros(n, bool), 1.5, info)
    local = arr - arr.mean(axis=0)
    idx, near = neighbour_table(local, k, radius)
    persistent = persistent_points(t - t.min(), idx, near, min_dt)
    flagged = floating_clusters(local, persistent, idx, near, radius)
    score = np.where(persistent, 0.0, np.where(flagged, 2.0, 1.0))
    info.update(points_tested=n, points_flagged=int(flagged.sum()),
                single_epoch=int((~persistent).sum()))
    return DetectorResult(score=score, flagged=flagged, critical_value=1.5, info=info)
