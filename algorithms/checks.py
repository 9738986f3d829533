"""Argument checks shared by the detectors (one message for one mistake, everywhere)."""

from __future__ import annotations

import numpy as np

from algorithms.errors import ParameterError


def check_xyz(xyz: np.ndarray) -> np.ndarray:
    """``xyz`` as an (n, 3) finite float64 array (no copy when it already is one).

    Raises ParameterError (also a ValueError) naming the problem.
    """
    arr = np.asarray(xyz, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ParameterError(f"xyz must have shape (n, 3), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ParameterError("xyz holds NaN or infinite coordinates")
    return arr
