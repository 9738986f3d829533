"""Spatial ordering and batching for the spatial detectors.

The patch detector fits one surface per point to its k nearest neighbours. Gathering all n
patches at once would need an (n, k, 3) array (1 GB for 1.1 M points and k = 40), so points are
processed in batches of spatially adjacent points: the cloud is cut into square XY tiles, tiles are
visited in row order and their points form consecutive batches. Neighbours come from one k-d tree
over the whole cloud, so a patch never depends on which tile or batch its point falls in (there is
no halo to get wrong; results are identical for any tile size, which the tests check).

The same XY grid cuts the cloud into the square sections of the section detector.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from algorithms.columns import column_max, column_min


def grid_cells(xy: np.ndarray, cell_size: float) -> tuple[np.ndarray, int]:
    """Linear index of the square XY cell of each point.

    Parameters
    ----------
    xy : (n, 2) float
        Coordinates; the grid origin is the lower-left corner of their bounding box, so shifting
        the cloud moves the grid with it.
    cell_size : float
        Cell edge (> 0), same unit as xy.

    Returns
    -------
    cell : (n,) int64
        Row-major cell index (row = y, column = x).
    n_columns : int
        Cells per row.
    """
    xy = np.asarray(xy, dtype=np.float64)
    if xy.shape[0] == 0:
        return np.zeros(0, dtype=np.int64), 1
    origin = column_min(xy)
    ij = np.floor((xy - origin) / cell_size).astype(np.int64)
    n_columns = int(ij[:, 0].max()) + 1
    return ij[:, 1] * n_columns + ij[:, 0], n_columns


def group_by_cell(cell: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points grouped by cell.

    Returns (order (n,), offsets (g + 1,)): ``order[offsets[j]:offsets[j + 1]]`` are the indices of
    the points of the j-th non-empty cell (cells in increasing index, points in input order).
    """
    order = np.argsort(cell, kind="stable")
    sorted_cells = cell[order]
    starts = np.flatnonzero(np.r_[True, sorted_cells[1:] != sorted_cells[:-1]]) if cell.size else []
    offsets = np.r_[np.asarray(starts, dtype=np.int64), cell.size].astype(np.int64)
    return order, offsets


def tile_size_for(xy: np.ndarray, points_per_tile: int) -> float:
    """Tile edge giving about ``points_per_tile`` points per tile at the cloud's mean XY density."""
    xy = np.asarray(xy, dtype=np.float64)
    if xy.shape[0] <= points_per_tile:
        return float("inf")
    extent = np.ptp(xy, axis=0)
    area = max(float(extent[0] * extent[1]), float(max(extent.max(), 1e-9)) ** 2 / xy.shape[0])
    return float(np.sqrt(area * points_per_tile / xy.shape[0]))


def spatial_batches(
    xy: np.ndarray,
    batch_points: int,
    tile_size: float | None = None,
    cell_points: int = 320,
) -> Iterator[np.ndarray]:
    """Indices of the points in spatially compact batches of at most ``batch_points`` points.

    Points are ordered tile by tile (tiles of ``tile_size``, default chosen for about
    ``batch_points`` points per tile), inside a tile by small cells of about ``cell_points``
    points (row by row), and the ordered list is cut into consecutive batches. Every point
    appears in exactly one batch. The fine order makes consecutive points neighbours, which
    halves the cost of the k-d tree queries and of gathering the patches (memory locality).
    """
    if batch_points < 1:
        raise ValueError(f"batch_points must be >= 1, got {batch_points}")
    n = np.asarray(xy).shape[0]
    if tile_size is None:
        tile_size = tile_size_for(xy, batch_points)
    cell_size = tile_size_for(xy, cell_points)
    fine = grid_cells(xy, cell_size)[0] if np.isfinite(cell_size) else np.zeros(n, np.int64)
    tile = grid_cells(xy, tile_size)[0] if np.isfinite(tile_size) else np.zeros(n, np.int64)
    order = np.lexsort((fine, tile))
    for start in range(0, n, batch_points):
        yield order[start : start + batch_points]


def cell_counts(points: np.ndarray, edge: float) -> np.ndarray:
    """(n,) how many of ``points`` (n, d) share each point's cell of a grid of ``edge`` metres
    (corner at their lowest coordinates)."""
    if len(points) == 0:
        return np.zeros(0, dtype=np.int64)
    ij = np.floor((points - column_min(points)) / edge).astype(np.int64)
    dims = column_max(ij) + 1
    if float(np.prod(dims.astype(np.float64))) < 2.0**62:  # one integer key per cell
        key = np.ravel_multi_index(ij.T, tuple(int(v) for v in dims))
        _, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
    else:
        _, inverse, counts = np.unique(ij, axis=0, return_inverse=True, return_counts=True)
    return counts[inverse.ravel()]


def kth_distance_within(points: np.ndarray, k: int, where: np.ndarray,
                        allowed: np.ndarray | None = None) -> np.ndarray:
    """(n,) for each point of the mask ``where`` (others 0) its distance to its k-th nearest
    point of ``points`` (n, d), itself counted first; inf for all when there are fewer than k.

    With ``allowed`` (n,), a point may get an upper bound of that distance instead, when the
    bound is at most its ``allowed`` and cheap: in a grid of cells whose diagonal is the
    smallest ``allowed`` of the mask, a cell holding k points holds each of them within its
    diagonal of k points. A tile's reach check asks only whether the distance fits in the
    halo, and in a dense cloud nearly every point answers so without a k-d tree query.
    """
    from algorithms.neighbours import neighbour_tree, query_nearest

    n, d = points.shape
    out = np.zeros(n)
    if not where.any():
        return out
    if n < k:
        return np.where(where, np.inf, 0.0)
    exact = where.copy()
    if allowed is not None:
        limit = float(np.min(allowed[where]))
        if 0.0 < limit < np.inf:
            bounded = where & (cell_counts(points, limit / np.sqrt(d)) >= k)
            out[bounded] = limit
            exact &= ~bounded
    if exact.any():
        dist, _ = query_nearest(neighbour_tree(points), points[exact], [k])
        out[exact] = dist[:, 0]
    return out
