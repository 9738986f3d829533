"""The value every outlier detector returns."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass
class DetectorResult:
    """Per-point outcome of one detector run on n points.

    Attributes
    ----------
    score : (n,) float64
        The detector's test statistic per point (|eq. 17| for temporal, T_i of eq. 31 for patch
        and section); NaN where the point was not tested.
    flagged : (n,) bool
        True where the score exceeds the critical value.
    critical_value : float or (n,) float64
        The threshold the score was compared against: one for all points, or one per point
        (``section``: t(n - 9) of the fit that tested the point; NaN where untested).
    info : dict
        Resolved parameters and facts for the statistics (sigma estimates, points tested, ...).
        Values must be JSON-serialisable.
    """

    score: np.ndarray
    flagged: np.ndarray
    critical_value: float | np.ndarray
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def tested(self) -> np.ndarray:
        return ~np.isnan(self.score)
