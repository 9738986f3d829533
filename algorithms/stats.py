"""Statistics helpers shared by the detectors: critical values, a robust scale estimate and the
noise of coordinate rounding."""

from __future__ import annotations

import math
from collections.abc import Iterable
from statistics import NormalDist

import numpy as np

#: Factor that makes the median absolute deviation a consistent estimator of a normal sigma
#: (1 / Phi^-1(3/4)).
MAD_TO_SIGMA = 1.482602218505602


def strided_sample(parts: Iterable[np.ndarray], max_points: int) -> np.ndarray:
    """Every ``max(1, m // max_points)``-th finite value of ``parts`` (consecutive pieces of one
    array, m finite values in all), the first included: the same sample whether the array comes
    whole or in pieces (a tiled run's per-point values in file order). Empty for m = 0."""
    parts = list(parts)
    finite = sum(int(np.count_nonzero(np.isfinite(p))) for p in parts)
    if finite == 0:
        return np.zeros(0)
    step = max(1, finite // max_points)
    kept, offset = [], 0
    for part in parts:
        v = np.asarray(part)[np.isfinite(part)]
        kept.append(v[(-offset) % step::step])
        offset += v.size
    return np.concatenate(kept)


def _check_alpha(alpha: float) -> float:
    alpha = float(alpha)
    if not 0.0 < alpha < 1.0:
        raise ValueError(f"alpha must be in (0, 1), got {alpha!r}")
    return alpha


def normal_critical_value(alpha: float) -> float:
    """Two-sided critical value of the standard normal: P(|Z| > c) = alpha.

    Used with eq. 17 (the standardised difference of the temporal detector).
    """
    return -NormalDist().inv_cdf(_check_alpha(alpha) / 2.0)


def t_critical_value(alpha: float, dof: float | np.ndarray) -> float | np.ndarray:
    """Two-sided critical value of Student's t with ``dof`` degrees of freedom.

    P(|T| > c) = alpha. ``dof`` may be a scalar or an array (any shape); the result has the same
    shape (a float for a scalar). Used with eq. 31 (t(n - 9) for the quadric patches). Entries
    with ``dof <= 0`` give NaN.
    """
    # Imported here: scipy.special costs about 0.1 s, which the temporal command need not pay
    # (and scipy.stats about a second).
    from scipy.special import stdtrit

    alpha = _check_alpha(alpha)
    dof_arr = np.asarray(dof, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        crit = -stdtrit(np.where(dof_arr > 0, dof_arr, np.nan), alpha / 2.0)
    if np.ndim(crit) == 0:
        return float(crit)
    return np.asarray(crit, dtype=np.float64)


def mad_sigma(x: np.ndarray) -> float:
    """Robust standard deviation: 1.4826 x median(|x - median(x)|), ignoring NaN.

    x : array of any shape. Returns NaN when x holds no finite value.
    """
    values = np.asarray(x, dtype=np.float64).ravel()
    values = values[np.isfinite(values)]  # a copy: the medians below may reorder it
    if values.size == 0:
        return float("nan")
    deviation = np.abs(values - np.median(values, overwrite_input=True))
    return float(MAD_TO_SIGMA * np.median(deviation, overwrite_input=True))


def rounding_sigma(scales: np.ndarray | None) -> np.ndarray:
    """(3,) standard deviation of coordinates rounded to the LAS ``scales`` (uniform rounding
    error: scale / sqrt(12)); zeros when not known. No estimate of the noise can be smaller:
    below it, a noise-free surface's rounding alone would be flagged."""
    if scales is None:
        return np.zeros(3)
    return np.abs(np.asarray(scales, dtype=np.float64)) / math.sqrt(12.0)
