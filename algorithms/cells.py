"""One int64 key a grid cell, in which a neighbour is a fixed offset away.

Voxel pieces, the small-piece ladder and ``transient``'s clusters look up each occupied cell's
neighbours (up to ``reach`` cells away along each axis) by searching sorted keys for the cell's
key plus an offset. The key ``(i * ny + j) * nz + k`` of a grid padded by ``reach`` cells does
that, but its range is the product of the grid's three extents, and a file with one stray
point kilometres off (a return at 0, 0, 0 in a projected frame, a height of -100 km) overflows
int64 with fine cells. Wrapped keys still differ by the right offset between neighbours, but a
distant cell's key may then land on a neighbour's, and indices read back from a key are wrong.
Such grids are squeezed first: along each axis a gap of more than ``reach`` between two occupied
indices is shortened to ``reach + 1``, which keeps every difference of at most ``reach`` and
every larger one larger than ``reach``, so the neighbours found are the same.
"""

from __future__ import annotations

import numpy as np

from algorithms.columns import column_max, column_min

#: Keys and key + offset stay below this (int64 with room for the offsets).
KEY_LIMIT = 2 ** 62


def cell_keys(ijk: np.ndarray, reach: int) -> tuple[np.ndarray, np.ndarray]:
    """(n,) int64 key of each cell of ``ijk`` (n, 3) int and the key's strides (3,) int64.

    Two cells whose indices differ by (di, dj, dk), each of at most ``reach`` (>= 0) in size,
    have keys that differ by ``di * strides[0] + dj * strides[1] + dk * strides[2]``; cells
    further apart along some axis never do. Keys sort the cells in the lexicographic order of
    their indices. Raises ValueError when even the squeezed grid overflows (millions of
    occupied, mutually distant indices along every axis)."""
    ijk = np.asarray(ijk, dtype=np.int64)
    if len(ijk) == 0:
        return np.zeros(0, dtype=np.int64), np.array([1, 1, 1], dtype=np.int64)
    local = ijk - column_min(ijk)
    if _cells_in_grid(local, reach) >= KEY_LIMIT:
        local = np.column_stack([_squeezed_axis(local[:, a], reach) for a in range(3)])
        if _cells_in_grid(local, reach) >= KEY_LIMIT:
            raise ValueError("too many distinct, mutually distant cells for one int64 key: "
                             "use larger cells")
    padded = local + reach
    dims = column_max(padded) + reach + 1
    strides = np.array([dims[1] * dims[2], dims[2], 1], dtype=np.int64)
    return padded @ strides, strides


def _cells_in_grid(local: np.ndarray, reach: int) -> int:
    """Cells of the grid padded by ``reach`` around the indices ``local`` (min 0), as a Python
    int (no overflow)."""
    total = 1
    for extent in column_max(local):
        total *= int(extent) + 2 * reach + 1
    return total


def _squeezed_axis(values: np.ndarray, reach: int) -> np.ndarray:
    """``values`` (n,) int with every gap between consecutive distinct values wider than
    ``reach`` shortened to ``reach + 1`` (order kept, min 0)."""
    distinct, inverse = np.unique(values, return_inverse=True)
    steps = np.minimum(np.diff(distinct), reach + 1)
    return np.concatenate([[0], np.cumsum(steps)])[inverse.ravel()]


def forward_offsets(reach: int) -> np.ndarray:
    """(m, 3) int64: the cell offsets of at most ``reach`` along every axis, one of each opposite
    pair and not (0, 0, 0): those > (0, 0, 0) in lexicographic order (13 for reach 1, 62 for 2).
    Visiting them from every cell visits each pair of neighbouring cells once."""
    span = range(-reach, reach + 1)
    return np.array([(i, j, k) for i in span for j in span for k in span if (i, j, k) > (0, 0, 0)],
                    dtype=np.int64).reshape(-1, 3)


def offset_keys(offsets: np.ndarray, strides: np.ndarray) -> np.ndarray:
    """(m,) int64 key step of each cell offset (m, 3) int under ``strides`` (:func:`cell_keys`)."""
    return np.asarray(offsets, dtype=np.int64) @ strides
