"""The TIN steps of the ground filter (:mod:`algorithms.ground`, steps 1-5 and 7).

Centring and spatial order, the lowest point per XY cell that enters the TIN, the low-outlier
test (step 3), the plane gradients of the triangles and the step-edge iteration (step 4: lower
and higher vertices, adjustment by the local slope of the non-edge neighbours, re-slope, repeat),
and the labels of the points left out of the TIN (step 7). The numba kernels live here, so
that importing :mod:`algorithms.ground` (for its parameters) stays cheap.
"""

from __future__ import annotations

import math

import numpy as np

from algorithms.columns import column_max, column_min
from algorithms.ground_raster import RasterGeometry
from algorithms.jit import njit
from algorithms.tin import delaunay, vertex_triangles

#: Quantile of the neighbours' z that a low outlier is compared with (step 3).
LOW_QUANTILE = 0.25


def z_offset(xyz: np.ndarray) -> float:
    """The elevation subtracted by :func:`centre` (the median z), added back to the results."""
    return float(np.median(xyz[:, 2]))


def centre(xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Local coordinates: XY minus the bounding-box centre, z minus the median z.

    Returns ``xy`` (n, 2) and ``z`` (n,), both float64.
    """
    lo, hi = column_min(xyz[:, :2]), column_max(xyz[:, :2])
    xy = xyz[:, :2] - 0.5 * (lo + hi)
    z = xyz[:, 2] - z_offset(xyz)
    return np.ascontiguousarray(xy), np.ascontiguousarray(z)


def spatial_order(xy: np.ndarray) -> np.ndarray:
    """A permutation that sorts the points by their cell of the low-outlier grid (row-major).

    Stable, so points with the same XY keep their order. Points near in space are then near in
    memory: Triangle triangulates about 30 % faster and the iteration's lookups hit the cache.
    """
    return np.argsort(_low_grid(xy)[0], kind="stable")


def _low_grid(xy: np.ndarray) -> tuple[np.ndarray, tuple[int, int]]:
    """Row-major cell index of each point in the grid of 1.6 mean point spacings, and its shape."""
    geo = RasterGeometry.fit(xy, spacings=1.6, min_cell=1e-6)
    return geo.flat, geo.shape


def lowest_per_xy(
    xy: np.ndarray, z: np.ndarray, cell: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """Group points by XY cell of ``cell`` metres (0: identical XY); keep the lowest of each group
    for the TIN.

    Returns
    -------
    rep : (n,) int64
        Index of the representative (lowest point) of each point's group.
    unique_idx : (u,) int64
        Sorted indices of the representatives.
    """
    n = z.shape[0]
    if cell > 0.0:
        key = RasterGeometry.at(xy, cell).flat
        order = np.argsort(key, kind="stable")
        sk = key[order]
        starts = np.ones(n, bool)
        starts[1:] = sk[1:] != sk[:-1]
    else:
        # one argsort of x + iy orders by x, then y (3x faster than a three-key lexsort)
        order = np.argsort(xy[:, 0] + 1j * xy[:, 1], kind="stable")
        sx, sy = xy[order, 0], xy[order, 1]
        starts = np.ones(n, bool)
        starts[1:] = (sx[1:] != sx[:-1]) | (sy[1:] != sy[:-1])
    if starts.all():  # the common case: one point per group
        idx = np.arange(n, dtype=np.int64)
        return idx, idx
    group = np.cumsum(starts) - 1
    zs = z[order]
    gmin = np.minimum.reduceat(zs, np.flatnonzero(starts))
    pos = np.flatnonzero(zs == gmin[group])
    gp = group[pos]
    keep = np.ones(pos.size, bool)
    keep[1:] = gp[1:] != gp[:-1]
    first = order[pos[keep]]  # lowest z of each group, smallest index among equal z
    rep = np.empty(n, np.int64)
    rep[order] = first[group]
    return rep, np.sort(first)


def triangulate(xy: np.ndarray, backend: str = "auto") -> tuple[np.ndarray, np.ndarray, str]:
    """Delaunay triangulation of distinct points in XY (:func:`algorithms.tin.delaunay`).

    Returns ``tri`` (m, 3) int64 vertex indices, ``nbr`` (m, 3) int64 edge-adjacent triangles
    (-1 on the hull) and the name of the triangulator used.
    """
    return delaunay(xy, backend)


@njit(cache=True)
def gradient_operators(xy: np.ndarray, tri: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per triangle the 2x2 inverse that maps vertex height differences to the plane gradient.

    With ``A = [[x1 - x0, y1 - y0], [x2 - x0, y2 - y0]]`` the plane through the three vertices has
    gradient ``g = A^-1 [z1 - z0, z2 - z0]``. Returns ``inv`` (m, 4) row-major A^-1 and
    ``valid`` (m,) bool (False for a degenerate triangle, whose slope is taken as 0).
    """
    m = tri.shape[0]
    inv = np.zeros((m, 4))
    valid = np.zeros(m, np.bool_)
    for t in range(m):
        a, b, c = tri[t, 0], tri[t, 1], tri[t, 2]
        ax, ay = xy[b, 0] - xy[a, 0], xy[b, 1] - xy[a, 1]
        bx, by = xy[c, 0] - xy[a, 0], xy[c, 1] - xy[a, 1]
        det = ax * by - ay * bx
        scale = (ax * ax + ay * ay) * (bx * bx + by * by)
        if det * det <= 1e-24 * scale or scale == 0.0:
            continue
        inv[t, 0] = by / det
        inv[t, 1] = -ay / det
        inv[t, 2] = -bx / det
        inv[t, 3] = ax / det
        valid[t] = True
    return inv, valid


@njit(cache=True)
def _gradient(t: int, tri: np.ndarray, z: np.ndarray, inv: np.ndarray) -> tuple[float, float]:
    a = tri[t, 0]
    d1 = z[tri[t, 1]] - z[a]
    d2 = z[tri[t, 2]] - z[a]
    return inv[t, 0] * d1 + inv[t, 1] * d2, inv[t, 2] * d1 + inv[t, 3] * d2


def triangle_slopes(xy: np.ndarray, z: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Slope of each triangle in degrees, (m,) float64: atan(|grad z|) of its plane."""
    inv, valid = gradient_operators(xy, tri)
    d1 = z[tri[:, 1]] - z[tri[:, 0]]
    d2 = z[tri[:, 2]] - z[tri[:, 0]]
    gx = inv[:, 0] * d1 + inv[:, 1] * d2
    gy = inv[:, 2] * d1 + inv[:, 3] * d2
    return np.where(valid, np.degrees(np.arctan(np.hypot(gx, gy))), 0.0)


@njit(cache=True)
def _lowest_vertex(t: int, tri: np.ndarray, z: np.ndarray) -> int:
    best = tri[t, 0]
    for k in range(1, 3):
        v = tri[t, k]
        if z[v] < z[best] or (z[v] == z[best] and v < best):
            best = v
    return best


@njit(cache=True)
def adjust_step_edges(
    xy: np.ndarray,
    z: np.ndarray,
    tri: np.ndarray,
    nbr: np.ndarray,
    grad: np.ndarray,
    is_edge: np.ndarray,
    edge_list: np.ndarray,
    tan_thr: np.ndarray,
    min_step: float,
    prop_sum: np.ndarray,
    prop_cnt: np.ndarray,
    touched: np.ndarray,
    productive: np.ndarray,
) -> int:
    """One round of proposals: for each step-edge triangle in ``edge_list``, the elevation its
    higher vertices would get from the lower vertex and the local slope of the non-edge neighbours.

    Accumulates into ``prop_sum``/``prop_cnt`` (zero on entry), lists the vertices that got a
    proposal in ``touched`` and marks in ``productive[i]`` whether ``edge_list[i]`` had a higher
    vertex; returns the number of touched vertices. Nothing in ``z`` changes here.
    """
    n_touched = 0
    for i in range(edge_list.shape[0]):
        t = edge_list[i]
        productive[i] = False
        low = _lowest_vertex(t, tri, z)
        gx = 0.0
        gy = 0.0
        cnt = 0
        for k in range(3):
            u = nbr[t, k]
            if u >= 0 and not is_edge[u]:
                gx += grad[u, 0]
                gy += grad[u, 1]
                cnt += 1
        if cnt > 0:
            gx /= cnt
            gy /= cnt
        for k in range(3):
            v = tri[t, k]
            if v == low:
                continue
            dx = xy[v, 0] - xy[low, 0]
            dy = xy[v, 1] - xy[low, 1]
            rise = z[v] - z[low]
            thr = 0.5 * (tan_thr[v] + tan_thr[low])
            if rise > min_step and rise > thr * math.hypot(dx, dy):
                productive[i] = True
                if prop_cnt[v] == 0:
                    touched[n_touched] = v
                    n_touched += 1
                # never below the lower vertex: an overshoot would make a pit that spreads
                prop_sum[v] += z[low] + max(gx * dx + gy * dy, 0.0)
                prop_cnt[v] += 1
    return n_touched


@njit(cache=True)
def iterate_step_edges(
    xy: np.ndarray,
    z: np.ndarray,
    tri: np.ndarray,
    nbr: np.ndarray,
    inv: np.ndarray,
    valid: np.ndarray,
    tan_thr: np.ndarray,
    min_step: float,
    max_iterations: int,
) -> tuple[np.ndarray, np.ndarray, list[int], list[int], int]:
    """The TIN step-edge iteration, in place on ``z`` (the adjusted elevations).

    Returns ``adjusted`` (n,) bool, ``pending`` (n,) bool (vertices a further round would still
    adjust), the number of step-edge triangles examined in each round (all of them in the first,
    then those with a higher vertex or a moved vertex),
    the number of vertices adjusted in each round, and the step-edge triangles left at the end.
    """
    n = z.shape[0]
    m = tri.shape[0]
    ptr, vt = vertex_triangles(tri, n)
    grad = np.zeros((m, 2))
    is_edge = np.zeros(m, np.bool_)
    tan2 = np.empty(m)
    n_edge = 0
    for t in range(m):  # step 1: slope of every triangle
        thr = (tan_thr[tri[t, 0]] + tan_thr[tri[t, 1]] + tan_thr[tri[t, 2]]) / 3.0
        tan2[t] = thr * thr
        if valid[t]:
            gx, gy = _gradient(t, tri, z, inv)
            grad[t, 0] = gx
            grad[t, 1] = gy
            if gx * gx + gy * gy > tan2[t]:
                is_edge[t] = True
                n_edge += 1
    edge_list = np.empty(n_edge, np.int64)
    j = 0
    for t in range(m):
        if is_edge[t]:
            edge_list[j] = t
            j += 1

    adjusted = np.zeros(n, np.bool_)
    prop_sum = np.zeros(n)
    prop_cnt = np.zeros(n, np.int64)
    touched = np.empty(n, np.int64)
    stamp = np.full(m, -1, np.int64)
    productive = np.empty(m, np.bool_)
    edges_per_round: list[int] = []
    moved_per_round: list[int] = []
    for it in range(max_iterations):
        if edge_list.shape[0] == 0:
            break
        edges_per_round.append(edge_list.shape[0])
        # step 2: lower vertex terrain, higher vertices get proposals from the local slope
        n_touched = adjust_step_edges(
            xy, z, tri, nbr, grad, is_edge, edge_list, tan_thr, min_step,
            prop_sum, prop_cnt, touched, productive,
        )
        moved_per_round.append(n_touched)
        if n_touched == 0:
            break
        # step 3: apply the mean proposal of each candidate; it becomes an object point
        for i in range(n_touched):
            v = touched[i]
            z[v] = prop_sum[v] / prop_cnt[v]
            adjusted[v] = True
            prop_sum[v] = 0.0
            prop_cnt[v] = 0
        # step 4: recompute the slopes of the modified triangles, collect the new step edges. A
        # step-edge triangle without a higher vertex (a steep but low step, e.g. noise between
        # close points) cannot produce one until a vertex of it moves: it is only re-examined
        # then, so that dense clouds do not revisit it in every round.
        cand = np.empty(edge_list.shape[0] + 12 * n_touched, np.int64)
        nc = 0
        for i in range(edge_list.shape[0]):
            t = edge_list[i]
            if productive[i]:
                stamp[t] = it
                cand[nc] = t
                nc += 1
        for i in range(n_touched):
            v = touched[i]
            for p in range(ptr[v], ptr[v + 1]):
                t = vt[p]
                if stamp[t] != it:
                    stamp[t] = it
                    if nc == cand.shape[0]:
                        grown = np.empty(2 * nc, np.int64)
                        grown[:nc] = cand[:nc]
                        cand = grown
                    cand[nc] = t
                    nc += 1
        k = 0
        for i in range(nc):
            t = cand[i]
            if valid[t]:
                gx, gy = _gradient(t, tri, z, inv)
                grad[t, 0] = gx
                grad[t, 1] = gy
                is_edge[t] = gx * gx + gy * gy > tan2[t]
            if is_edge[t]:
                cand[k] = t
                k += 1
        edge_list = cand[:k].copy()
    # vertices that a further round would still move: the front of an unfinished peel
    pending = np.zeros(n, np.bool_)
    productive = np.empty(edge_list.shape[0], np.bool_)
    n_touched = adjust_step_edges(
        xy, z, tri, nbr, grad, is_edge, edge_list, tan_thr, min_step,
        prop_sum, prop_cnt, touched, productive,
    )
    for i in range(n_touched):
        pending[touched[i]] = True
    remaining = 0
    for t in range(m):
        if is_edge[t]:
            remaining += 1
    return adjusted, pending, edges_per_round, moved_per_round, remaining


def resolve_duplicates(
    z: np.ndarray,
    z_adj: np.ndarray,
    rep: np.ndarray,
    unique_idx: np.ndarray,
    is_ground: np.ndarray,
    tol: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Label the points left out of the TIN (same XY as a lower point) from their representative."""
    dup = rep != np.arange(rep.size)
    if not dup.any():
        return is_ground, z_adj
    r = rep[dup]
    z_adj = z_adj.copy()
    z_adj[dup] = z_adj[r]
    is_ground = is_ground.copy()
    is_ground[dup] = is_ground[r] & (np.abs(z[dup] - z_adj[r]) < tol)
    z_adj[dup & is_ground] = z[dup & is_ground]
    return is_ground, z_adj


def _low_reference(xy: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Per point the lower quartile of the z in the 3 x 3 block of grid cells around it, (n,).

    Cells are 1.6 mean point spacings wide, so a block holds about 24 points: a cheap
    stand-in for the k nearest neighbours (a k-d tree query costs more than the whole TIN).
    """
    flat, shape = _low_grid(xy)
    order = np.argsort(flat, kind="stable")
    ptr = np.searchsorted(flat[order], np.arange(shape[0] * shape[1] + 1))
    ref_cell = _block_quartiles(z[order], ptr, int(shape[0]), int(shape[1]), LOW_QUANTILE)
    return ref_cell[flat]


@njit(cache=True)
def _block_quartiles(
    z_sorted: np.ndarray, ptr: np.ndarray, nx: int, ny: int, q: float
) -> np.ndarray:
    """For each cell the q-quantile (lower order statistic) of z over its 3 x 3 block."""
    out = np.full(nx * ny, np.nan)
    buf = np.empty(z_sorted.shape[0])
    for i in range(nx):
        for j in range(ny):
            c = i * ny + j
            if ptr[c + 1] == ptr[c]:
                continue
            m = 0
            for di in range(-1, 2):
                for dj in range(-1, 2):
                    a, b = i + di, j + dj
                    if a < 0 or b < 0 or a >= nx or b >= ny:
                        continue
                    cc = a * ny + b
                    for p in range(ptr[cc], ptr[cc + 1]):
                        buf[m] = z_sorted[p]
                        m += 1
            out[c] = _select(buf, m, int(q * (m - 1)))
    return out


@njit(cache=True)
def _select(buf: np.ndarray, m: int, k: int) -> float:
    """The k-th smallest of ``buf[:m]`` (0-based) by quickselect, reordering ``buf[:m]``."""
    lo, hi = 0, m - 1
    while lo < hi:
        pivot = buf[(lo + hi) // 2]
        i, j = lo, hi
        while i <= j:
            while buf[i] < pivot:
                i += 1
            while buf[j] > pivot:
                j -= 1
            if i <= j:
                buf[i], buf[j] = buf[j], buf[i]
                i += 1
                j -= 1
        if k <= j:
            hi = j
        elif k >= i:
            lo = i
        else:
            break
    return buf[k]


def find_low_outliers(
    xy: np.ndarray, z: np.ndarray, depth: float
) -> tuple[np.ndarray, np.ndarray]:
    """Points more than ``depth`` metres below the lower quartile of their ~24 neighbours.

    Multi-path returns lie well below the terrain, alone or in small clusters; a point next to a
    building still has terrain neighbours in its lower quartile, so it is not caught. Returns the
    (n,) bool mask and the (n,) reference elevations (the lower quartiles).
    """
    if xy.shape[0] < 4:
        return np.zeros(xy.shape[0], bool), z.copy()
    ref = _low_reference(xy, z)
    return z < ref - depth, ref


@njit(cache=True)
def _find(parent: np.ndarray, v: int) -> int:
    root = v
    while parent[root] != root:
        root = parent[root]
    while parent[v] != root:  # path compression
        parent[v], v = root, parent[v]
    return root


@njit(cache=True)
def enclosed_components(
    xy: np.ndarray,
    z: np.ndarray,
    tri: np.ndarray,
    nbr: np.ndarray,
    candidate: np.ndarray,
    tan_thr: np.ndarray,
    min_step: float,
    min_drop_fraction: float,
) -> np.ndarray:
    """Candidates whose connected region of the TIN is stepped down on (almost) all sides.

    Candidates (the iteration's object points) are joined into regions by the TIN edges between
    them. Each edge from a region to a point outside it is a *drop* when the region's end is
    higher by more than ``min_step`` and by more than ``tan_thr`` times the edge's length (a step
    edge). A region is *enclosed* when at least ``min_drop_fraction`` of its boundary edges are
    drops and it touches neither the TIN's hull (where its boundary is unknown) nor nothing.
    Returns (n,) bool: True for the candidates in enclosed regions.
    """
    n = z.shape[0]
    parent = np.arange(n)
    m = tri.shape[0]
    for t in range(m):
        for k in range(3):
            u = nbr[t, k]
            if u >= 0 and u < t:
                continue  # each edge once: from the triangle with the larger index, or the hull
            a = tri[t, (k + 1) % 3]
            b = tri[t, (k + 2) % 3]
            if candidate[a] and candidate[b]:
                ra, rb = _find(parent, a), _find(parent, b)
                if ra != rb:
                    parent[max(ra, rb)] = min(ra, rb)
    boundary = np.zeros(n, np.int64)
    drops = np.zeros(n, np.int64)
    on_hull = np.zeros(n, np.bool_)
    for t in range(m):
        for k in range(3):
            u = nbr[t, k]
            if u >= 0 and u < t:
                continue
            a = tri[t, (k + 1) % 3]
            b = tri[t, (k + 2) % 3]
            if u < 0:
                if candidate[a]:
                    on_hull[_find(parent, a)] = True
                if candidate[b]:
                    on_hull[_find(parent, b)] = True
            if candidate[a] == candidate[b]:
                continue
            inner, outer = (a, b) if candidate[a] else (b, a)
            r = _find(parent, inner)
            boundary[r] += 1
            rise = z[inner] - z[outer]
            dist = math.hypot(xy[inner, 0] - xy[outer, 0], xy[inner, 1] - xy[outer, 1])
            if rise > min_step and rise > 0.5 * (tan_thr[inner] + tan_thr[outer]) * dist:
                drops[r] += 1
    out = np.zeros(n, np.bool_)
    for v in range(n):
        if candidate[v]:
            r = _find(parent, v)
            out[v] = (not on_hull[r] and boundary[r] > 0
                      and drops[r] >= min_drop_fraction * boundary[r])
    return out
