"""Parameters and input arrays of the temporal detector, checked and resolved.

:class:`TemporalParameters` declares the parameters (:mod:`algorithms.params`);
``check_params`` resolves them for the computation (sigma per axis, the critical value of eq. 17)
and ``check_arrays`` checks the input arrays, for the batch and the streaming detector alike.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from algorithms.errors import MissingDimensionError, ParameterError
from algorithms.params import Parameters, param
from algorithms.stats import normal_critical_value


@dataclass(frozen=True)
class TemporalParameters(Parameters):
    """Algorithm (a): moving fixed-interval smoother along scan lines (eqs. 1-17)."""

    n1: int = param(5, "Points before the tested point in the window.", ge=1, le=100)
    n2: int = param(5, "Points after the tested point in the window.", ge=1, le=100)
    sigma: float | tuple[float, float, float] | Literal["auto"] = param(
        "auto", "Standard deviation of each coordinate in metres (> 0; one number or one per "
        "axis X, Y, Z), or 'auto' for a robust estimate from the data (reported in the "
        "statistics).", gt=0)
    alpha: float = param(0.001, "Two-sided significance level.", gt=0, lt=0.5)
    max_gap: float | Literal["auto"] = param(
        "auto", "Time step in seconds (> 0) above which a scan line is split into segments; "
        "'auto' = 5 x the group's median positive time step.", gt=0)
    group_by: Literal["point_source_id", "none"] = param(
        "point_source_id", "Dimension that separates the scanners, or 'none'.")

    def check(self) -> None:
        if self.n1 + self.n2 < 3:
            # A quadratic in time (eqs. 1-3) needs three neighbours besides the tested point,
            # otherwise the point carries the whole fit and eq. 15 divides by zero.
            raise ParameterError(
                f"n1 + n2 must be >= 3 (a quadratic needs three neighbours to predict a point), "
                f"got n1={self.n1}, n2={self.n2}")


@dataclass
class ResolvedParameters:
    """The parameters as the computation uses them, 'auto' left as None to be estimated."""

    n1: int
    n2: int
    alpha: float
    critical_value: float
    sigma: np.ndarray | None  # (3,) metres, None for "auto"
    max_gap: float | None  # seconds, None for "auto"


def check_params(
    n1: int, n2: int, sigma: float | str | Sequence[float], alpha: float, max_gap: float | str
) -> ResolvedParameters:
    """The declared checks (:class:`TemporalParameters`), then sigma and max_gap resolved."""
    p = TemporalParameters(n1=n1, n2=n2, sigma=sigma, alpha=alpha, max_gap=max_gap)
    sigma_arr = None if p.sigma == "auto" else np.broadcast_to(
        np.asarray(p.sigma, dtype=np.float64), (3,)).copy()
    gap = None if p.max_gap == "auto" else float(p.max_gap)
    return ResolvedParameters(int(p.n1), int(p.n2), float(p.alpha),
                              normal_critical_value(p.alpha), sigma_arr, gap)


def check_arrays(
    xyz: np.ndarray, gps_time: np.ndarray | None, group: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """xyz (n, 3) and gps_time (n,) as float64, group (n,) integers or None; else an error."""
    if gps_time is None:
        raise MissingDimensionError("the temporal detector needs gps_time, which this data lacks")
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ParameterError(f"xyz must have shape (n, 3), got {xyz.shape}")
    t = np.asarray(gps_time, dtype=np.float64)
    if t.shape != (xyz.shape[0],):
        raise ParameterError(f"gps_time must have shape ({xyz.shape[0]},), got {t.shape}")
    if group is not None:
        group = np.asarray(group)
        if group.shape != t.shape:
            raise ParameterError(f"group must have shape ({t.size},), got {group.shape}")
        if not np.issubdtype(group.dtype, np.integer):
            raise ParameterError(f"group must hold integers (scanner ids), got {group.dtype}")
    return xyz, t, group
