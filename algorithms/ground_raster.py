"""The raster steps of the ground filter (:mod:`algorithms.ground`, steps 6 and 8).

A grid of square cells over the points (:class:`RasterGeometry`), the lowest point per cell,
pull-push filling of empty cells, the progressive morphological opening that tells terraces from
objects (step 6), and the ground surface sampled bilinearly under every point (step 8). The
numba kernels live here, so that importing :mod:`algorithms.ground` stays cheap.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from algorithms.columns import column_max, column_min
from algorithms.jit import njit

#: Openings at most in the progressive terrace check (step 6); larger radii are stepped evenly.
MAX_OPENINGS = 16


@dataclass
class RasterGeometry:
    """A grid of square cells over the points' XY extent and each point's cell.

    Attributes: ``lo`` (2,) the grid's lower-left corner, ``cell`` the cell size in metres,
    ``shape`` (nx, ny) and ``flat`` (n,) the row-major cell index of each point.
    """

    lo: np.ndarray
    cell: float
    shape: tuple[int, int]
    flat: np.ndarray

    @classmethod
    def fit(
        cls, xy: np.ndarray, spacings: float = 1.0, min_cell: float = 1e-3
    ) -> RasterGeometry:
        """Cells ``spacings`` mean point spacings wide (mean spacing = sqrt(area / n)), at least
        ``min_cell`` metres."""
        ext = np.maximum(column_max(xy) - column_min(xy), 1e-9)
        return cls.at(xy, max(spacings * float(np.sqrt(ext[0] * ext[1] / xy.shape[0])), min_cell))

    @classmethod
    def at(cls, xy: np.ndarray, cell: float) -> RasterGeometry:
        """Cells of ``cell`` metres from the lower-left corner of the points' extent."""
        lo = column_min(xy)
        ext = np.maximum(column_max(xy) - lo, 1e-9)
        shape = (ext / cell).astype(np.int64) + 1
        ij = ((xy - lo) / cell).astype(np.int64)
        return cls(lo, cell, (int(shape[0]), int(shape[1])), ij[:, 0] * shape[1] + ij[:, 1])


def lowest_per_cell(
    geo: RasterGeometry, z: np.ndarray, mask: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The lowest z per cell (of the points in ``mask``, default all): grid and filled-cell mask."""
    flat, vals = (geo.flat, z) if mask is None else (geo.flat[mask], z[mask])
    grid = np.full(geo.shape[0] * geo.shape[1], np.inf)
    np.minimum.at(grid, flat, vals)
    grid = grid.reshape(geo.shape)
    return grid, np.isfinite(grid)


def fill_pull_push(grid: np.ndarray, filled: np.ndarray) -> np.ndarray:
    """Fill the cells where ``filled`` is False by pull-push interpolation; others are kept.

    Pull: each coarser level holds per 2 x 2 block the mean of its filled cells and a weight, the
    number of filled cells capped at 1. Push: from the coarsest level down, a cell becomes
    ``w * own + (1 - w) * parent``. An all-empty grid gives zeros.
    """
    if filled.all():
        return grid
    levels = [(np.where(filled, grid, 0.0), filled.astype(np.float64))]
    while max(levels[-1][0].shape) > 1:
        levels.append(_pull(*levels[-1]))
    val = levels[-1][0]
    for own, wt in reversed(levels[:-1]):
        val = _push(own, wt, val)
    return np.where(filled, grid, val)


@njit(cache=True)
def _pull(val: np.ndarray, wt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One coarser pyramid level: weighted block means over 2 x 2 cells, weights capped at 1."""
    nx, ny = val.shape
    cx, cy = (nx + 1) // 2, (ny + 1) // 2
    sv = np.zeros((cx, cy))
    sw = np.zeros((cx, cy))
    for i in range(nx):
        for j in range(ny):
            w = wt[i, j]
            if w > 0.0:
                sv[i // 2, j // 2] += val[i, j] * w
                sw[i // 2, j // 2] += w
    for i in range(cx):
        for j in range(cy):
            if sw[i, j] > 0.0:
                sv[i, j] /= sw[i, j]
                sw[i, j] = min(sw[i, j], 1.0)
    return sv, sw


@njit(cache=True)
def _push(own: np.ndarray, wt: np.ndarray, parent: np.ndarray) -> np.ndarray:
    """A level from its own values and the filled coarser one: ``w * own + (1 - w) * parent``."""
    nx, ny = own.shape
    out = np.empty((nx, ny))
    for i in range(nx):
        for j in range(ny):
            w = wt[i, j]
            out[i, j] = w * own[i, j] + (1.0 - w) * parent[i // 2, j // 2]
    return out


def opening_radii(window: float, cell: float, most: int = MAX_OPENINGS) -> np.ndarray:
    """Window radii in cells, 1 up to half of ``window``: every one, or ``most`` evenly stepped."""
    top = max(int(round(window / (2.0 * cell))), 1)
    if top <= most:
        return np.arange(1, top + 1)
    return np.unique(np.round(np.linspace(1, top, most)).astype(np.int64))


@njit(cache=True)
def _filter_rows(a: np.ndarray, r: int, take_max: bool) -> np.ndarray:
    """Running min (or max) over ``2 r + 1`` cells along each row, edges extended (van Herk /
    Gil-Werman: two block-wise prefix scans, about three comparisons per cell for any window).

    A window at least as long as the row always reaches one of its ends, so it is the prefix
    extreme up to its right end or the suffix extreme from its left end: two scans of the row,
    no padding (mobile strips are narrower than the largest windows of step 6).
    """
    nx, ny = a.shape
    if 2 * r + 1 >= ny:
        return _filter_rows_wide(a, r, take_max)
    w = 2 * r + 1
    length = ny + 2 * r
    padded = -(-length // w) * w
    out = np.empty_like(a)
    p = np.empty(padded, a.dtype)
    g = np.empty(padded, a.dtype)
    h = np.empty(padded, a.dtype)
    for i in range(nx):
        for j in range(padded):
            src = min(max(j - r, 0), ny - 1)
            p[j] = a[i, src]
        for b in range(0, padded, w):
            g[b] = p[b]
            for j in range(b + 1, b + w):
                g[j] = max(g[j - 1], p[j]) if take_max else min(g[j - 1], p[j])
            h[b + w - 1] = p[b + w - 1]
            for j in range(b + w - 2, b - 1, -1):
                h[j] = max(h[j + 1], p[j]) if take_max else min(h[j + 1], p[j])
        for j in range(ny):
            out[i, j] = max(h[j], g[j + w - 1]) if take_max else min(h[j], g[j + w - 1])
    return out


@njit(cache=True)
def _filter_rows_wide(a: np.ndarray, r: int, take_max: bool) -> np.ndarray:
    """:func:`_filter_rows` for 2 r + 1 >= row length: window [j - r, j + r] clipped to the row
    starts at 0 (j <= r: prefix extreme up to j + r) or else ends at the row's end (suffix
    extreme from j - r)."""
    nx, ny = a.shape
    out = np.empty_like(a)
    prefix = np.empty(ny, a.dtype)
    suffix = np.empty(ny, a.dtype)
    for i in range(nx):
        prefix[0] = a[i, 0]
        for j in range(1, ny):
            prefix[j] = max(prefix[j - 1], a[i, j]) if take_max else min(prefix[j - 1], a[i, j])
        suffix[ny - 1] = a[i, ny - 1]
        for j in range(ny - 2, -1, -1):
            suffix[j] = max(suffix[j + 1], a[i, j]) if take_max else min(suffix[j + 1], a[i, j])
        for j in range(ny):
            out[i, j] = prefix[min(ny - 1, j + r)] if j <= r else suffix[j - r]
    return out


def square_opening(grid: np.ndarray, r: int) -> np.ndarray:
    """Grey opening with a (2r+1) x (2r+1) square, edges extended (scipy's ``mode="nearest"``)."""
    eroded = _filter_rows(np.ascontiguousarray(_filter_rows(grid, r, False).T), r, False)
    return _filter_rows(np.ascontiguousarray(_filter_rows(eroded, r, True).T), r, True)


def progressive_object_cells(
    grid: np.ndarray, cell: float, window: float, slope: float
) -> np.ndarray:
    """Progressive morphological filter (Zhang et al. 2003; SMRF, Pingel et al. 2013) on a raster.

    Opens ``grid`` with squares of radius r (:func:`opening_radii`); a cell whose opening at
    radius r lies more than ``slope * r * cell`` below the opening at the previous radius (the grid
    itself before the first) is an object cell. Returns the (nx, ny) bool mask. Works in float32
    (half the memory traffic; elevations are centred, so a float32 step is below 0.1 mm).
    """
    grid = np.ascontiguousarray(grid, dtype=np.float32)
    obj = np.zeros(grid.shape, bool)
    prev = grid
    for r in opening_radii(window, cell):
        opened = square_opening(grid, int(r))
        obj |= prev - opened > np.float32(slope * r * cell)
        prev = opened
    return obj


def ground_surface(
    geo: RasterGeometry, xy: np.ndarray, z: np.ndarray, is_ground: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The ground surface under every point and its grade (step 8), both (n,).

    Lowest ground point per cell, the other cells filled by pull-push, sampled bilinearly between
    cell centres; grade = |grad| of the filled raster by differences.
    """
    grid, filled = lowest_per_cell(geo, z, is_ground)
    surface = fill_pull_push(grid, filled)
    # a raster one cell thin (a narrow strip of points) has no slope across it
    gx = np.gradient(surface, geo.cell, axis=0) if geo.shape[0] > 1 else np.zeros(geo.shape)
    gy = np.gradient(surface, geo.cell, axis=1) if geo.shape[1] > 1 else np.zeros(geo.shape)
    return bilinear(surface, np.hypot(gx, gy), (xy - geo.lo) / geo.cell - 0.5)


@njit(cache=True)
def bilinear(
    a: np.ndarray, b: np.ndarray, ij: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Two rasters sampled bilinearly at fractional cell coordinates ``ij`` (n, 2), where cell
    (i, j) has its value at (i, j); outside the raster the nearest edge value is taken (as
    ``scipy.ndimage.map_coordinates(order=1, mode="nearest")``)."""
    nx, ny = a.shape
    n = ij.shape[0]
    out_a = np.empty(n)
    out_b = np.empty(n)
    for k in range(n):
        fi = min(max(ij[k, 0], 0.0), nx - 1.0)
        fj = min(max(ij[k, 1], 0.0), ny - 1.0)
        i0 = min(int(fi), max(nx - 2, 0))
        j0 = min(int(fj), max(ny - 2, 0))
        i1 = min(i0 + 1, nx - 1)
        j1 = min(j0 + 1, ny - 1)
        ti = fi - i0
        tj = fj - j0
        w00 = (1.0 - ti) * (1.0 - tj)
        w01 = (1.0 - ti) * tj
        w10 = ti * (1.0 - tj)
        w11 = ti * tj
        out_a[k] = w00 * a[i0, j0] + w01 * a[i0, j1] + w10 * a[i1, j0] + w11 * a[i1, j1]
        out_b[k] = w00 * b[i0, j0] + w01 * b[i0, j1] + w10 * b[i1, j0] + w11 * b[i1, j1]
    return out_a, out_b


def box_mean(grid: np.ndarray, r: int) -> np.ndarray:
    """Mean over the (2r+1) x (2r+1) square around each cell, edges extended (as
    ``scipy.ndimage.uniform_filter(mode="nearest")``), by running sums along each axis."""
    out = np.asarray(grid, dtype=np.float64)
    if r <= 0:
        return out.copy()
    for axis in (0, 1):
        pad = [(0, 0), (0, 0)]
        pad[axis] = (r + 1, r)
        c = np.cumsum(np.pad(out, pad, mode="edge"), axis=axis)
        hi = np.take(c, np.arange(2 * r + 1, c.shape[axis]), axis=axis)
        lo = np.take(c, np.arange(0, c.shape[axis] - 2 * r - 1), axis=axis)
        out = (hi - lo) / (2 * r + 1)
    return out


def terrain_grade(
    geo: RasterGeometry, xy: np.ndarray, lowest: np.ndarray, window: float
) -> np.ndarray:
    """The terrain's own grade (tan of its slope) under every point, (n,); zeros for window 0.

    The filled lowest-point raster is opened with a square of ``window`` metres (objects narrower
    than the window are cut away, the terrain below them kept: an opening leaves a plane of any
    slope unchanged) and averaged over the same square (the trend of the relief at that scale);
    the grade is the magnitude of the trend's gradient, sampled bilinearly. Steep hillsides get
    a high grade, flat land with buildings a low one: the step-edge threshold of a triangle is
    the terrain's grade plus tan(slope_threshold), so a hillside is not peeled like a roof.
    """
    n = xy.shape[0]
    r = int(round(window / (2.0 * geo.cell)))
    if window <= 0 or r < 1:
        return np.zeros(n)
    trend = box_mean(square_opening(np.ascontiguousarray(lowest, dtype=np.float64), r), r)
    gx = np.gradient(trend, geo.cell, axis=0) if geo.shape[0] > 1 else np.zeros(geo.shape)
    gy = np.gradient(trend, geo.cell, axis=1) if geo.shape[1] > 1 else np.zeros(geo.shape)
    g = np.hypot(gx, gy)
    return bilinear(g, g, (xy - geo.lo) / geo.cell - 0.5)[0]
