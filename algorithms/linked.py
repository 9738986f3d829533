"""Connected components of points linked within a radius, without listing the links.

Two points are linked when they lie at most ``radius`` apart; the components of that graph are
``transient``'s clusters of single-epoch points. Listing every link (a k-d tree's pairs) costs
memory and time with the number of links, and a vehicle standing still piles hundreds of
returns within a radius of each other. Here the points are put in cubic cells of edge
``radius / sqrt(3)`` (times 1 - 1e-9 against rounding), so that:

* two points of one cell are always linked (the cell's diagonal is shorter than the radius):
  each cell is one piece from the start;
* two linked points lie at most two cells apart along each axis (radius / edge < 2);
* two cells already in one component need no look at their points; else their points are
  compared until the first link joins them.

A union-find over the points (path halving) records the joins. Compiled with numba.
"""

from __future__ import annotations

import numpy as np

from algorithms.cells import cell_keys, forward_offsets, offset_keys
from algorithms.columns import column_min
from algorithms.jit import njit

#: Cell edge as a share of the radius: the diagonal sqrt(3) x edge stays under the radius.
CELL_SHARE = (1.0 - 1e-9) / np.sqrt(3.0)
#: Cells this far apart along each axis may hold linked points (radius / edge < 2).
LINK_REACH = 2


def radius_components(xyz: np.ndarray, radius: float) -> tuple[int, np.ndarray]:
    """(number of components, (n,) int64 label 0..c-1 of each point) of the graph linking the
    points of ``xyz`` (n, 3) that lie at most ``radius`` apart (radius > 0)."""
    n = len(xyz)
    if n == 0:
        return 0, np.zeros(0, dtype=np.int64)
    if not radius > 0:
        raise ValueError("radius must be > 0")
    xyz = np.ascontiguousarray(xyz, dtype=np.float64)
    ijk = np.floor((xyz - column_min(xyz)) / (radius * CELL_SHARE)).astype(np.int64)
    key, strides = cell_keys(ijk, reach=LINK_REACH)
    order = np.argsort(key, kind="stable")
    keys, starts = np.unique(key[order], return_index=True)
    offsets = offset_keys(forward_offsets(LINK_REACH), strides)
    root = _join_cells(xyz[order], keys, np.r_[starts, n].astype(np.int64), offsets,
                       float(radius) ** 2)
    roots, label = np.unique(root, return_inverse=True)
    out = np.empty(n, dtype=np.int64)
    out[order] = label.ravel()
    return len(roots), out


@njit(cache=True)
def _find(parent: np.ndarray, i: int) -> int:
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


@njit(cache=True)
def _cells_linked(xyz: np.ndarray, a0: int, a1: int, b0: int, b1: int, r2: float) -> bool:
    """Whether a point of rows a0:a1 lies within sqrt(r2) of one of rows b0:b1."""
    for p in range(a0, a1):
        for q in range(b0, b1):
            d2 = ((xyz[p, 0] - xyz[q, 0]) ** 2 + (xyz[p, 1] - xyz[q, 1]) ** 2
                  + (xyz[p, 2] - xyz[q, 2]) ** 2)
            if d2 <= r2:
                return True
    return False


@njit(cache=True)
def _join_cells(xyz: np.ndarray, keys: np.ndarray, bounds: np.ndarray, offsets: np.ndarray,
                r2: float) -> np.ndarray:
    """Each point's root (rows of ``xyz`` sorted by cell; cell u holds rows
    bounds[u]:bounds[u + 1] and has key keys[u])."""
    m = len(keys)
    parent = np.empty(len(xyz), dtype=np.int64)
    for u in range(m):
        parent[bounds[u]:bounds[u + 1]] = bounds[u]  # a cell is one piece
    for u in range(m):
        for off in offsets:
            v = np.searchsorted(keys, keys[u] + off)
            if v >= m or keys[v] != keys[u] + off:
                continue
            a, b = _find(parent, bounds[u]), _find(parent, bounds[v])
            if a == b:
                continue
            if _cells_linked(xyz, bounds[u], bounds[u + 1], bounds[v], bounds[v + 1], r2):
                parent[max(a, b)] = min(a, b)
    for i in range(len(xyz)):
        parent[i] = _find(parent, i)
    return parent
