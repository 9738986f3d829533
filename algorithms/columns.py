"""Per-column minimum and maximum of an (n, d) array.

``a.min(axis=0)`` on a C-ordered (n, 3) array walks the rows three values at a time and is
5-10 times slower than reducing each column on its own (numpy 2.4: 17-30 ms against 3 ms for
0.9 M rows). Minima and maxima are exact, so both give the same values; the bounds of clouds,
grids and cell indices are taken here.
"""

from __future__ import annotations

import numpy as np


def column_min(a: np.ndarray) -> np.ndarray:
    """(d,) the smallest value of each column of ``a`` (n, d), n >= 1; ``a.min(axis=0)``."""
    return np.array([a[:, j].min() for j in range(a.shape[1])], dtype=a.dtype)


def column_max(a: np.ndarray) -> np.ndarray:
    """(d,) the largest value of each column of ``a`` (n, d), n >= 1; ``a.max(axis=0)``."""
    return np.array([a[:, j].max() for j in range(a.shape[1])], dtype=a.dtype)
