"""The k nearest neighbours of points, in an order that follows the points alone.

A patch's sums run over its points in the order of its row here, so that a point's patch, and
its bits, are the same from any k-d tree build, from a tile and from the whole cloud, and for
every copy of a repeated point (:func:`nearest_in_order`).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from algorithms.columns import column_min
from algorithms.jit import njit, prange
from algorithms.threads import worker_threads

#: Metres: queries are asked cell by cell of this XY edge (:func:`query_nearest`).
QUERY_CELL = 1.0
#: Fewer queries than this are asked in their own order (sorting them would cost more).
ORDERED_QUERIES_MIN = 50_000
#: Queries asked at a time: the answers of a block (about 7 MB at k = 26) are reused memory,
#: not fresh pages.
ORDERED_BLOCK = 32_768


def neighbour_tree(xyz: np.ndarray) -> cKDTree:
    """The k-d tree nearest neighbours are found in: leaves of 32 points split at the midpoint,
    not the median (on a 1.2 M-point mobile cloud it builds in 0.19 s instead of 0.32 s and
    answers k = 26 queries in 2.2 s instead of 3.1 s). The distances found do not depend on
    the tree; where it matters which of the points tied at the k-th distance are taken, the
    callers take them by index."""
    return cKDTree(xyz, leafsize=32, balanced_tree=False)


def space_order(points: np.ndarray) -> np.ndarray:
    """(m,) a permutation of ``points`` (m, d >= 2) that groups them by XY cell of
    :data:`QUERY_CELL` metres (cells row by row)."""
    ij = np.floor(points[:, :2] / QUERY_CELL)
    ij -= column_min(ij)
    key = ij[:, 0] * (ij[:, 1].max() + 1.0) + ij[:, 1]  # exact below 2**53 cells
    return np.argsort(key, kind="stable")


def query_nearest(tree: cKDTree, queries: np.ndarray, k: int | list[int],
                  **options: float) -> tuple[np.ndarray, np.ndarray]:
    """``tree.query(queries, k, workers=worker_threads(), **options)``, asked cell by cell
    (:func:`space_order`) and answered in the queries' order. Neighbouring queries then walk
    the same branches of the tree while they are in the cache: the same answers in about 80 %
    of the time for queries in a file's time order."""
    if len(queries) < ORDERED_QUERIES_MIN:
        return tree.query(queries, k=k, workers=worker_threads(), **options)
    order = space_order(queries)
    out_dist = out_idx = None
    for s in range(0, len(order), ORDERED_BLOCK):
        rows = order[s:s + ORDERED_BLOCK]
        dist, idx = tree.query(queries[rows], k=k, workers=worker_threads(), **options)
        if out_dist is None:
            out_dist = np.empty((len(queries), *dist.shape[1:]), dtype=dist.dtype)
            out_idx = np.empty((len(queries), *idx.shape[1:]), dtype=idx.dtype)
        out_dist[rows], out_idx[rows] = dist, idx
    return out_dist, out_idx


def nearest_in_order(tree: cKDTree, xyz: np.ndarray, query: np.ndarray, k: int) -> np.ndarray:
    """(m, k) the k nearest points of ``xyz[query]``, each row the query's own point first (the
    lowest index among its copies) and the others by index; points tied at the k-th distance
    are taken by index.

    So the patch of a point depends on the points alone, not on the k-d tree's build (a tile
    and the whole cloud index the same points in the same order), and its sums run in one
    order.
    """
    kk = min(k + 1, len(xyz))
    dist, nbr = query_nearest(tree, xyz[query], kk)
    dist, nbr = dist.reshape(len(query), kk), nbr.reshape(len(query), kk)
    if kk > k:
        rows = np.flatnonzero(dist[:, k - 1] == dist[:, k])
        if rows.size:
            nbr[rows, :k] = _ties_by_index(tree, xyz, query[rows], dist[rows, k - 1], k)
    nbr = np.ascontiguousarray(nbr[:, :k])
    _own_first_then_by_index(nbr, np.ascontiguousarray(dist[:, :k] == 0.0))
    return nbr


@njit(cache=True, parallel=True)
def _own_first_then_by_index(rows: np.ndarray, at_query: np.ndarray) -> None:
    """Order each row of ``rows`` (m, k) in place: first the lowest index among the points at
    the query's own coordinates (``at_query`` (m, k)), then the others by index.

    Copies of a point (a scanner standing still) come from the k-d tree in an order of its
    build; by index, every copy's patch holds its points in one order (the same sums, the same
    bits), and so does a tile's. Insertion sort: k is tens.
    """
    for r in prange(rows.shape[0]):
        row = rows[r]
        at = 0
        for i in range(row.size):
            if at_query[r, i] and row[i] < row[at]:
                at = i
        row[0], row[at] = row[at], row[0]
        for i in range(2, row.size):
            value = row[i]
            j = i - 1
            while j >= 1 and row[j] > value:
                row[j + 1] = row[j]
                j -= 1
            row[j + 1] = value


def _ties_by_index(tree: cKDTree, xyz: np.ndarray, points: np.ndarray, radius: np.ndarray,
                   k: int) -> np.ndarray:
    """(m, k) the k nearest of each of ``points``, nearest first, equal distances by index;
    ``radius`` (m,) is each one's k-th distance. One ball query and one sort for all of them
    (mobile clouds tie often: points on a scan grid, a vehicle standing still)."""
    row, flat = ball_candidates(tree, xyz, points, radius)
    d2 = np.sum((xyz[flat] - xyz[points][row]) ** 2, axis=1)
    flat = flat[np.lexsort((flat, d2, row))]  # by row, then distance, then index
    first = np.searchsorted(row, np.arange(len(points)))  # row is sorted
    return flat[first[:, None] + np.arange(k)]


def ball_candidates(tree: cKDTree, xyz: np.ndarray, points: np.ndarray, radius: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Every point within ``radius`` (m,) of each of ``points`` (m,) (a hair further, so that
    the points at exactly that distance are in), in one ball query: (row, index) pairs as
    flat int64 arrays, grouped by row in order. Where a k-d tree broke ties at the k-th
    neighbour in its own order, these are what ties are broken again from."""
    near = tree.query_ball_point(xyz[points], radius * (1 + 1e-9), workers=worker_threads())
    sizes = np.fromiter((len(n) for n in near), dtype=np.int64, count=len(near))
    flat = np.concatenate(near).astype(np.int64)
    return np.repeat(np.arange(len(points)), sizes), flat


@njit(cache=True, parallel=True)
def by_distance_then_index(dist: np.ndarray, idx: np.ndarray) -> None:
    """Sort each row of ``dist`` and ``idx`` (m, k) in place by distance, equal distances by
    index. Rows come from a k-d tree in distance order already, with ties in the tree's own
    order, so insertion sort moves only the tied entries."""
    for r in prange(dist.shape[0]):
        d, i = dist[r], idx[r]
        for a in range(1, d.size):
            dv, iv = d[a], i[a]
            b = a - 1
            while b >= 0 and (d[b] > dv or (d[b] == dv and i[b] > iv)):
                d[b + 1], i[b + 1] = d[b], i[b]
                b -= 1
            d[b + 1], i[b + 1] = dv, iv


@njit(cache=True, parallel=True)
def first_other_points(dist: np.ndarray, idx: np.ndarray, own: np.ndarray, n: int, k: int,
                       radius: float, out_idx: np.ndarray, out_near: np.ndarray) -> np.ndarray:
    """The k nearest *other* points of each query from a k-d tree's answer.

    dist, idx (m, kq): the tree's rows (missing neighbours as index n); own (m,): each query's
    own index, skipped wherever it appears (points that coincide may come before it). Writes
    out_idx (m, k) and out_near (m, k) (within ``radius``; False for padding) and returns (m,)
    bool: the rows whose k-th and (k+1)-th other points lie equally far within ``radius``
    (a tie the tree broke in its own order)."""
    m, kq = dist.shape
    tied = np.zeros(m, dtype=np.bool_)
    for r in prange(m):
        taken = 0
        kth = np.inf
        for c in range(kq):
            j = idx[r, c]
            if j == own[r] or j >= n:
                continue
            if taken < k:
                out_idx[r, taken] = j
                out_near[r, taken] = dist[r, c] <= radius
                kth = dist[r, c]
                taken += 1
            else:
                tied[r] = dist[r, c] == kth and kth <= radius
                break
    return tied


@njit(cache=True, parallel=True)
def any_near_apart(values: np.ndarray, idx: np.ndarray, near: np.ndarray,
                   least: float) -> np.ndarray:
    """(m,) bool: row r of a neighbour table (``idx``, ``near``, each (m, k)) holds a neighbour
    marked near whose value differs from the row's own, ``values[r]``, by at least ``least``
    (``values`` (m,) own then indexed by ``idx``). What ``np.any(near & (|values[idx] -
    values[:, None]| >= least), axis=1)`` gives, without its (m, k) temporaries."""
    out = np.zeros(idx.shape[0], dtype=np.bool_)
    for r in prange(idx.shape[0]):
        own = values[r]
        for c in range(idx.shape[1]):
            if near[r, c] and abs(values[idx[r, c]] - own) >= least:
                out[r] = True
                break
    return out
