"""The ``temporal`` detector: the paper's moving fixed-interval smoother (algorithm (a), eqs. 1-17).

Each scanner's points, ordered by GPS time and cut into line segments at time gaps, give three
series X(k), Y(k), Z(k). For every point k a quadratic in time (the alpha-beta-gamma state model,
eqs. 1-4) is fitted to the window [k - n1, k + n2]; eq. 15 predicts z(k) from the neighbours alone,
eq. 16 gives the variance of z(k) - z_p(k) and eq. 17 the standardised difference, which is tested
against the two-sided normal critical value. A point's score is the largest |eq. 17| of X, Y, Z.

Modules, one job each:

- ``smoother``: the per-window equations, vectorised over blocks of windows: ``smoother_weights``
  (eqs. 11, 14), ``predict_from_window`` (eq. 15), ``difference_variance`` (eq. 16) and
  ``standardised_difference`` (eq. 17);
- ``windows``: each point's window (``window_bounds``) and the evaluation of many windows, by
  slices or gathered rows, on all cores (``window_differences``, ``segment_differences``);
- ``compiled``: the same evaluation compiled with numba, window by window with the same bits,
  for long series (imported only when one runs);
- ``segments``: scan lines cut into segments at time gaps (``cut_segments``, ``max_gap``);
- ``parameters``: :class:`TemporalParameters` and their resolution, shared by both detectors;
- ``batch``: ``detect_temporal``, the robust sigma estimate and the scores;
- ``stream``: ``TemporalStream``, the same detector over chunks (identical results for fixed
  sigma and max_gap).

Plain numpy at import (scipy only for t-values, numba only for ``compiled``, both lazily):
importing this package is cheap.
"""

from __future__ import annotations

from algorithms.temporal.batch import detect_temporal
from algorithms.temporal.parameters import TemporalParameters
from algorithms.temporal.stream import TemporalStream

__all__ = ["TemporalParameters", "TemporalStream", "detect_temporal"]
