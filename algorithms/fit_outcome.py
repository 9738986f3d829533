"""What every quadric fit of eqs. 18-31 shares, without the fit: its size, its outcome codes and
the smallest surface that can flag anything.

The adjustment itself (:mod:`algorithms.quadric`) is compiled with numba; the detectors read
these facts when their parameters are checked, which the command line does for every detector
when it starts, so they live apart from it.
"""

from __future__ import annotations

import math

import numpy as np

from algorithms.stats import t_critical_value

#: Unknowns of eq. 18 and the redundancy lost to them (10 parameters, 1 constraint).
N_PARAMS = 10
DOF_LOSS = 9

# Fit outcome codes (QuadricFit.status): why a fit gives no T_i, for the detectors' statistics.
#: The iteration converged: T_i (eq. 31) is valid.
CONVERGED = 0
#: ||da|| stayed above the tolerance through every stage of the iteration.
NOT_CONVERGED = 1
#: The points lie nearly on a line (:data:`algorithms.quadric.COLLINEAR_RATIO`): no unique
#: quadric.
COLLINEAR = 2
#: The bordered normal equations were singular or a weight of eq. 30 was zero or not finite.
SINGULAR = 3
#: No redundancy: at most 9 points (10 parameters, 1 constraint).
TOO_FEW_POINTS = 4


def min_patch_size(alpha: float) -> int:
    """Smallest n for which sqrt(n - 9) > t(n - 9) at ``alpha``: below it eq. 31 cannot flag."""
    n = DOF_LOSS + 1
    while not math.sqrt(n - DOF_LOSS) > t_critical_value(alpha, n - DOF_LOSS):
        n += 1
    return n


def can_flag(n: int | np.ndarray, alpha: float) -> np.ndarray:
    """True where a surface of n points can flag anything at ``alpha`` (sqrt(n-9) > t(n-9))."""
    n = np.asarray(n)
    return n >= min_patch_size(alpha)
