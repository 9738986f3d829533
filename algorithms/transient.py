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
   scene, occluded elsewhere; so is a cluster wider than ``max_extent`` (the side of its XY
   bounding box): no vehicle or barrier arm is that long, a single-pass survey's street seen
   once is; a cluster attached to nothing and no wider than that floats;
4. a floating cluster is flagged only where its place was seen at another moment, else being
   seen once says nothing about motion (one scanner on one pass sees every static surface once,
   and a surface hidden from the other scanner is seen once too). Both must hold:

   - *the scene beside it was seen again*: of the returns the same scanner fired just before
     and just after the cluster's returns (its neighbours along the scan line, by GPS time),
     at least half are persistent;
   - *the place under or over it was seen again*: at least half of its points have a
     persistent point within ``radius`` in plan (the road under a moving car was seen by the
     other scanner or pass; nobody sees the ground under a parked car's roof).

Score per point: 0 persistent, 1 single-epoch in an attached, wide or unrevisited cluster, 2
single-epoch in a floating, revisited cluster (flagged; critical value 1.5). numpy/scipy
(cKDTree) and the compiled clusters of :mod:`algorithms.linked`.

Over a file of any size (:func:`point_facts`, :func:`cluster_decisions`), with the whole
cloud's result and no halo wider than ``2 * radius``: step 1 and what steps 3-4 read around a
point (a persistent neighbour within ``radius``, a persistent point within ``radius`` in plan)
depend only on the points within ``2 * radius``, so a pass over tiles with that much around
them gives them for every point; the scan-line neighbours (the returns fired just before and
after) may lie anywhere, a pass over the whole file in time order gives them
(:func:`scan_line_neighbours` on every point's time and scanner); the clusters are the
connected components of the single-epoch points (:func:`algorithms.linked.radius_components`,
whose memory does not grow with the number of links), and every decision of steps
3-4 is a count, a bounding box or an "any" over a cluster's points, summed over the file.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from algorithms.errors import ParameterError
from algorithms.params import Parameters, param
from algorithms.result import DetectorResult
from algorithms.threads import worker_threads


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
    max_extent: float = param(
        40.0, "Metres: a single-epoch cluster whose XY bounding box is wider than this is static "
        "scene seen once (a single pass's street, a facade hidden from the other scanner), not a "
        "moving object. 40 m: over 1.5 times the longest lorry or articulated bus (25.25 m) and "
        "3 times a barrier arm (up to 12 m), leaving room for the smear of an object scanned "
        "while it moves along (one keeping nearly the vehicle's speed can look longer still). "
        "A tiled run reads this much plus radius around each tile.", gt=0, le=1000)
    free_space_radius: float = param(
        0.006, "With a trajectory file: metres a beam must pass within a point to see through "
        "it (free-space evidence).", gt=0, le=10)
    free_space_margin: float = param(
        0.08, "With a trajectory file: metres a beam must end beyond a point to count (the "
        "least: more where the beam meets the surface at its end at a grazing angle).",
        ge=0, le=100)
    free_space_min_rays: int = param(
        1, "With a trajectory file: beams that saw through a point to flag it.", ge=1, le=1000)
    free_space_hit_ratio: float = param(
        0.5, "With a trajectory file: a point seen through stays flagged only while the returns "
        "of other pulses on its own beam (within free_space_radius across, free_space_margin "
        "along) are at most this many times the beams that saw through it: a surface is "
        "returned to, the edge of one about half the time, a droplet almost never.",
        ge=0, le=1e6)
    stop_free_space: bool = param(
        True, "Where a profile scanner stood still (its returns of a tenth of a second lie on "
        "the profile it records 0.3 s later), also flag the points that at least 5 of its beams "
        "of that second passed and that its own beam returned to at most 0.1 times as often "
        "(exhaust and dust at a standstill, which lie in the scan plane like everything the "
        "standing scanner sees). Needs no trajectory: the scanner's position is fitted from "
        "the second's own points.")
    lever_arms: tuple[tuple[int, float, float, float], ...] = param(
        (),
        "With a trajectory file: [point_source_id, forward, left, up] metres of each scanner "
        "from the trajectory's reference point in the vehicle frame (heading from the "
        "trajectory's motion), as the system's calibration gives them. A scanner not listed is "
        "placed from its own points (a profile scanner's beams turn at one rate in one plane "
        "through it); one that cannot be placed gives no free-space evidence.")


#: Points per kNN batch.
KNN_BATCH = 262_144


def neighbour_table(xyz: np.ndarray, k: int, radius: float, rows: np.ndarray | None = None
                    ) -> tuple[np.ndarray, np.ndarray]:
    """(m, k) int64 indices of the k nearest other points of each of the points ``rows`` (None:
    every point, m = n) and (m, k) bool "within radius". Only the neighbours within ``radius``
    are read, so the search stops there: the entries beyond it are padding (index 0, False),
    as for clouds with fewer than k + 1 points.

    Points as far as the k-th (within ``radius``) are taken in index order
    (:func:`_tied_neighbours`), so the table is the same in any part of the cloud that holds
    the points within ``radius`` in the same order (a tile's region is in file order)."""
    n = len(xyz)
    rows = np.arange(n) if rows is None else np.asarray(rows, dtype=np.int64)
    m = len(rows)
    kq = min(k + 2, n)  # one more than needed: a tie at the k-th shows
    idx = np.zeros((m, k), dtype=np.int64)
    near = np.zeros((m, k), dtype=bool)
    if m == 0:
        return idx, near
    from algorithms.neighbours import first_other_points, neighbour_tree, query_nearest

    tree = neighbour_tree(xyz)
    for s in range(0, m, KNN_BATCH):
        batch = rows[s:s + KNN_BATCH]
        d, j = query_nearest(tree, xyz[batch], kq,
                             distance_upper_bound=np.nextafter(radius, np.inf))
        d, j = d.reshape(-1, kq), j.reshape(-1, kq).astype(np.int64, copy=False)
        # each point itself is dropped (not necessarily column 0 when points coincide)
        tied = first_other_points(d, j, batch, n, k, radius, idx[s:s + len(j)],
                                  near[s:s + len(j)])
        rows_tied = np.flatnonzero(tied)
        if rows_tied.size:
            idx[s + rows_tied], near[s + rows_tied] = _tied_neighbours(
                tree, xyz, batch[rows_tied], d[rows_tied], k, radius)
    return idx, near


def _tied_neighbours(tree, xyz: np.ndarray, points: np.ndarray, d: np.ndarray, k: int,
                     radius: float) -> tuple[np.ndarray, np.ndarray]:
    """(m, k) the k nearest other points of each of ``points`` where several lie as far as the
    k-th, and whether each is within ``radius``: by distance, then index (the order in which
    the whole cloud and a tile hold them alike). ``d`` (m, kq): the tree's distances of each
    (its largest finite one reaches past the tie). One ball query and one sort for all."""
    from algorithms.neighbours import ball_candidates

    far = np.max(np.where(np.isfinite(d), d, -np.inf), axis=1)
    row, cand = ball_candidates(tree, xyz, points, far)
    other = cand != points[row]
    cand, row = cand[other], row[other]
    dist = np.sqrt(np.sum((xyz[cand] - xyz[points[row]]) ** 2, axis=1))
    order = np.lexsort((cand, dist, row))  # by row, then distance, then index
    cand, dist = cand[order], dist[order]
    first = np.searchsorted(row[order], np.arange(len(points)))
    take = first[:, None] + np.arange(k)
    return cand[take], dist[take] <= radius


def persistent_points(gps_time: np.ndarray, idx: np.ndarray, near: np.ndarray,
                      min_dt: float) -> np.ndarray:
    """(n,) bool: a neighbour within radius was recorded at least min_dt seconds apart.

    The times are compared as given (not moved to the cloud's first time), so a run over any
    part of the file computes the same differences."""
    from algorithms.neighbours import any_near_apart

    return any_near_apart(np.ascontiguousarray(gps_time, dtype=np.float64), idx, near,
                          float(min_dt))


def scan_line_neighbours(gps_time: np.ndarray, source: np.ndarray | None
                         ) -> tuple[np.ndarray, np.ndarray]:
    """(n,) int64 index of the return the same scanner fired just before and just after each
    one (-1 at a scanner's first and last return); source None: one scanner. Equal times
    keep the points' order."""
    n = len(gps_time)
    src = np.zeros(n, dtype=np.int64) if source is None else np.asarray(source, dtype=np.int64)
    order = np.lexsort((gps_time, src))
    before = np.full(n, -1, dtype=np.int64)
    after = np.full(n, -1, dtype=np.int64)
    same = src[order[1:]] == src[order[:-1]]
    before[order[1:][same]] = order[:-1][same]
    after[order[:-1][same]] = order[1:][same]
    return before, after


def stream_scan_lines(gps_time: np.ndarray, source: np.ndarray, use: np.ndarray,
                      before: np.ndarray, after: np.ndarray, chunk: int = 4_000_000,
                      chunk_done: Callable[[], None] | None = None) -> bool:
    """:func:`scan_line_neighbours` of the points ``use`` (n,) bool, written into ``before`` and
    ``after`` (n,) as indices among all n points (-1: none, and for points not used), in one
    pass of ``chunk`` points at a time: for files whose returns come in time order per scanner
    (a drive written as recorded), where the order by time is the points' own. Returns False,
    leaving the outputs unfinished, at the first return earlier than its scanner's previous
    one (then sort). The arrays may be memory maps: memory is a chunk's (``chunk_done``, called
    after each chunk, may give the maps' pages back)."""
    last_time: dict[int, float] = {}
    last_index: dict[int, int] = {}
    n = len(gps_time)
    for s in range(0, n, chunk):
        rows = s + np.flatnonzero(use[s:s + chunk])
        before[s:s + chunk] = -1
        after[s:s + chunk] = -1
        src = np.asarray(source[rows], dtype=np.int64)
        order = np.argsort(src, kind="stable")  # each scanner's returns, in file order
        rows, src, t = rows[order], src[order], np.asarray(gps_time[rows][order])
        same = src[1:] == src[:-1]
        if np.any(same & (t[1:] < t[:-1])):
            return False
        before[rows[1:][same]] = rows[:-1][same]
        after[rows[:-1][same]] = rows[1:][same]
        for first in np.flatnonzero(np.r_[True, ~same]):
            scanner = int(src[first])
            if scanner in last_time:
                if t[first] < last_time[scanner]:
                    return False
                before[rows[first]] = last_index[scanner]
                after[last_index[scanner]] = rows[first]
        for final in np.flatnonzero(np.r_[~same, True]):
            last_time[int(src[final])] = float(t[final])
            last_index[int(src[final])] = int(rows[final])
        if chunk_done is not None:
            chunk_done()
    return True


@dataclass(frozen=True)
class ScanLineSide:
    """Each point's scan-line neighbour on one side (before or after), as step 4 reads it:
    ``present`` (n,) bool, the scanner fired one; ``row`` (n,) int64, its row among the points
    at hand (-1: none, or elsewhere in the file); ``persistent`` (n,) bool, it is persistent."""

    present: np.ndarray
    row: np.ndarray
    persistent: np.ndarray


def scan_line_sides(neighbours: tuple[np.ndarray, np.ndarray], persistent: np.ndarray
                    ) -> tuple[ScanLineSide, ScanLineSide]:
    """Both sides of :func:`scan_line_neighbours` when every neighbour is at hand."""
    before, after = (
        ScanLineSide(j >= 0, j, (j >= 0) & persistent[np.maximum(j, 0)]) for j in neighbours)
    return before, after


def cluster_widths(xy: np.ndarray, label: np.ndarray, n_comp: int) -> np.ndarray:
    """(n_comp,) the longer side of each cluster's XY bounding box (xy: (m, 2) its points)."""
    lo = np.full((n_comp, 2), np.inf)
    hi = np.full((n_comp, 2), -np.inf)
    np.minimum.at(lo, label, xy)
    np.maximum.at(hi, label, xy)
    return np.max(hi - lo, axis=1)


def revisited_clusters(xyz: np.ndarray, persistent: np.ndarray, single: np.ndarray,
                       label: np.ndarray, n_comp: int, sides: tuple[ScanLineSide, ...],
                       radius: float) -> np.ndarray:
    """(n_comp,) bool: the cluster's place was seen at another moment (step 4 of the module
    docstring): at least half of its scan-line neighbours outside it are persistent, and at
    least half of its points have a persistent point within ``radius`` in plan."""
    n = len(xyz)
    cluster = np.full(n, -1, dtype=np.int64)
    cluster[single] = label
    flanks = np.zeros(n_comp)
    seen_flanks = np.zeros(n_comp)
    for side in sides:
        j = side.row[single]
        inside = (j >= 0) & (cluster[np.maximum(j, 0)] == label)
        outside = side.present[single] & ~inside
        np.add.at(flanks, label[outside], 1.0)
        np.add.at(seen_flanks, label[outside], side.persistent[single][outside])
    beside = (flanks > 0) & (2.0 * seen_flanks >= flanks)
    seen = np.flatnonzero(persistent)
    if seen.size == 0:
        return np.zeros(n_comp, dtype=bool)
    covered = covered_in_plan(xyz[seen, :2], xyz[single, :2], radius)
    size = np.bincount(label, minlength=n_comp)
    under = 2.0 * np.bincount(label, weights=covered, minlength=n_comp) >= size
    return beside & under


def covered_in_plan(seen_xy: np.ndarray, xy: np.ndarray, radius: float) -> np.ndarray:
    """(m,) bool: a point of ``seen_xy`` lies within ``radius`` (inclusive) of each of ``xy``
    in plan. The nearest one within reach is enough: counting every point of the ball costs
    thousands a query under a wall."""
    from algorithms.neighbours import neighbour_tree

    nearest, _ = neighbour_tree(seen_xy).query(
        xy, k=1, distance_upper_bound=np.nextafter(radius, np.inf), workers=worker_threads())
    return nearest <= radius


@dataclass(frozen=True)
class Clusters:
    """Steps 3-4 on n points, three (n,) bool: ``floating`` single-epoch points whose cluster
    touches no persistent point and is no wider than ``max_extent``, ``flagged`` those of them
    whose place was seen at another moment, ``wide`` single-epoch points of clusters wider than
    ``max_extent``."""

    floating: np.ndarray
    flagged: np.ndarray
    wide: np.ndarray


def floating_clusters(xyz: np.ndarray, persistent: np.ndarray, touches: np.ndarray,
                      radius: float, sides: tuple[ScanLineSide, ...] | None = None,
                      max_extent: float = np.inf) -> Clusters:
    """Steps 3-4 (:class:`Clusters`). ``touches`` (n,) bool: a persistent point is among the
    point's neighbours (:func:`neighbour_table`) within ``radius`` (read on single-epoch
    points). ``sides``: the scan-line neighbours (:func:`scan_line_sides`) that
    :func:`revisited_clusters` reads; None: every floating cluster counts as revisited."""
    n = len(xyz)
    single = np.flatnonzero(~persistent)
    floating, flagged, wide = (np.zeros(n, dtype=bool) for _ in range(3))
    if single.size == 0:
        return Clusters(floating, flagged, wide)
    from algorithms.linked import radius_components

    n_comp, label = radius_components(xyz[single], radius)  # memory: no list of links
    attached = np.zeros(n_comp, dtype=bool)
    attached[label[touches[single]]] = True
    too_wide = cluster_widths(xyz[single, :2], label, n_comp) > max_extent
    wide[single[too_wide[label]]] = True
    free = ~attached & ~too_wide
    floating[single[free[label]]] = True
    if sides is None:
        return Clusters(floating, floating.copy(), wide)
    revisited = revisited_clusters(xyz, persistent, single, label, n_comp, sides, radius)
    flagged[single[(free & revisited)[label]]] = True
    return Clusters(floating, flagged, wide)


def touching_persistent(idx: np.ndarray, near: np.ndarray, persistent: np.ndarray) -> np.ndarray:
    """(m,) bool: a persistent point is among the table's neighbours within radius."""
    return np.any(near & persistent[idx], axis=1)


def _checked(xyz: np.ndarray, n_name: str, arrays: dict[str, np.ndarray]) -> np.ndarray:
    """xyz as (n, 3) float64, refusing bad shapes and values of it and of ``arrays``."""
    arr = np.asarray(xyz, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ParameterError(f"xyz must have shape (n, 3), got {arr.shape}")
    for name, values in arrays.items():
        if np.shape(values) != (len(arr),):
            raise ParameterError(f"xyz must have shape (n, 3) and {name} ({n_name},), got "
                                 f"{arr.shape} and {np.shape(values)}")
    if not np.all(np.isfinite(arr)):
        raise ParameterError("xyz or gps_time holds NaN or infinite values")
    return arr


def _result(persistent: np.ndarray, clusters: Clusters, info: dict) -> DetectorResult:
    flagged = clusters.flagged
    score = np.where(persistent, 0.0, np.where(flagged, 2.0, 1.0))
    info.update(points_tested=len(persistent), points_flagged=int(flagged.sum()),
                single_epoch=int((~persistent).sum()),
                floating_not_revisited=int((clusters.floating & ~flagged).sum()),
                single_epoch_wide=int(clusters.wide.sum()))
    return DetectorResult(score=score, flagged=flagged, critical_value=1.5, info=info)


def detect_transient(
    xyz: np.ndarray,
    gps_time: np.ndarray,
    source: np.ndarray | None = None,
    *,
    k: int = 24,
    radius: float = 0.2,
    min_dt: float = 0.5,
    max_extent: float = 40.0,
    centre: bool = True,
) -> DetectorResult:
    """Flag floating single-epoch clusters (module docstring).

    xyz (n, 3) metres, gps_time (n,) seconds (finite), source (n,) the scanner of each return
    (point_source_id; None: one scanner). ``centre``: move xyz to its mean first (False: xyz is
    in a local frame already, and a tiled run, :func:`point_facts`, computes on the same
    numbers). Returns a DetectorResult with score (n,) in {0, 1, 2}, flagged = score ==
    2, critical_value 1.5.
    """
    arr = _checked(xyz, "n", {"gps_time": gps_time})
    t = np.asarray(gps_time, dtype=np.float64)
    if not np.all(np.isfinite(t)):
        raise ParameterError("xyz or gps_time holds NaN or infinite values")
    if source is not None and np.shape(source) != (len(arr),):
        raise ParameterError(f"source must have shape ({len(arr)},), got {np.shape(source)}")
    TransientParameters(k=k, radius=radius, min_dt=min_dt, max_extent=max_extent)
    n = len(arr)
    info = {"k": int(k), "radius": float(radius), "min_dt": float(min_dt),
            "max_extent": float(max_extent), "points": n}
    if n < 2:
        info.update(points_tested=n, points_flagged=0, single_epoch=n, floating_not_revisited=0,
                    single_epoch_wide=0)
        return DetectorResult(np.zeros(n), np.zeros(n, bool), 1.5, info)
    local = arr - arr.mean(axis=0) if centre else arr
    idx, near = neighbour_table(local, k, radius)
    persistent = persistent_points(t, idx, near, min_dt)
    sides = scan_line_sides(scan_line_neighbours(t, source), persistent)
    clusters = floating_clusters(local, persistent, touching_persistent(idx, near, persistent),
                                 radius, sides, max_extent)
    return _result(persistent, clusters, info)


# --------------------------------------------------------------------------- over a whole file


def point_facts(xyz: np.ndarray, gps_time: np.ndarray, *, k: int, radius: float,
                min_dt: float) -> dict[str, np.ndarray]:
    """Steps 1-2 and what step 3-4 read of each point's surroundings, (n,) bool each:
    ``persistent``; for single-epoch points ``touches`` (a persistent point among its
    neighbours within ``radius``, :func:`touching_persistent`) and ``covered`` (a persistent
    point within ``radius`` in plan, as :func:`revisited_clusters` counts). Exact for the points
    with every point within ``2 * radius`` of them at hand (a tile's region), in the frame and
    order the whole cloud's run uses."""
    arr = np.asarray(xyz, dtype=np.float64)
    n = len(arr)
    touches, covered = np.zeros(n, dtype=bool), np.zeros(n, dtype=bool)
    if n < 2:
        return {"persistent": np.zeros(n, dtype=bool), "touches": touches, "covered": covered}
    idx, near = neighbour_table(arr, k, radius)
    persistent = persistent_points(np.asarray(gps_time, dtype=np.float64), idx, near, min_dt)
    single = np.flatnonzero(~persistent)
    touches[single] = touching_persistent(idx[single], near[single], persistent)
    seen = np.flatnonzero(persistent)
    if seen.size and single.size:
        covered[single] = covered_in_plan(arr[seen, :2], arr[single, :2], radius)
    return {"persistent": persistent, "touches": touches, "covered": covered}


def cluster_decisions(xyz: np.ndarray, facts: dict[str, np.ndarray], sides: tuple[
        ScanLineSide, ...], *, radius: float, max_extent: float) -> tuple[Clusters, int]:
    """Steps 3-4 on the single-epoch points of a whole file, from their :func:`point_facts`
    (``touches``, ``covered``) and scan-line ``sides`` (``row``: the neighbour's position among
    these points, -1 when it is not one of them): :class:`Clusters` over them, as
    :func:`floating_clusters` decides them on the whole cloud, and the number of clusters."""
    from algorithms.linked import radius_components

    n_comp, label = radius_components(xyz, radius)
    attached = np.zeros(n_comp, dtype=bool)
    attached[label[facts["touches"]]] = True
    too_wide = cluster_widths(xyz[:, :2], label, n_comp) > max_extent
    free = ~attached & ~too_wide
    flanks, seen_flanks = np.zeros(n_comp), np.zeros(n_comp)
    for side in sides:
        j = side.row
        inside = (j >= 0) & (label[np.maximum(j, 0)] == label)
        outside = side.present & ~inside
        np.add.at(flanks, label[outside], 1.0)
        np.add.at(seen_flanks, label[outside], side.persistent[outside])
    beside = (flanks > 0) & (2.0 * seen_flanks >= flanks)
    size = np.bincount(label, minlength=n_comp)
    under = 2.0 * np.bincount(label, weights=facts["covered"], minlength=n_comp) >= size
    revisited = beside & under
    floating = free[label]
    return Clusters(floating, (free & revisited)[label], too_wide[label]), n_comp
