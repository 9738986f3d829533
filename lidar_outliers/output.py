"""The result format: the extra-bytes dimensions a flagged cloud gains.

``outlier_flags`` (uint16) holds one bit per outlier detector that flagged the point (the bits are
the detectors' declared ``flag_bit``); ``<detector>_score`` (float32) holds each outlier detector's
score, NaN where it did not test the point.
"""

from __future__ import annotations

import numpy as np

FLAGS_DIMENSION = "outlier_flags"
FLAGS_DTYPE = np.uint16
#: Bits of ``outlier_flags``: at most this many outlier detectors.
FLAG_BITS_AVAILABLE = 16


def score_dimension(detector: str) -> str:
    """Name of the float32 extra dimension that holds a detector's score."""
    return f"{detector}_score"


def result_dimensions(detectors: list[str]) -> list[tuple[str, type, str]]:
    """(name, type, description) of the extra dimensions of a result: the flag bitmask and one
    score per outlier detector that ran."""
    dims: list[tuple[str, type, str]] = [(FLAGS_DIMENSION, FLAGS_DTYPE, "bit per outlier detector")]
    dims += [(score_dimension(d), np.float32, f"{d} score") for d in detectors]
    return dims
