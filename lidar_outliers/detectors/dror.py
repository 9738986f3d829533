"""``dror``: the dynamic-radius outlier removal baseline of Charron et al. (2018) for spinning
sensors (:mod:`algorithms.dror`)."""

from __future__ import annotations

import numpy as np

from algorithms.dror import DrorParameters
from algorithms.result import DetectorResult
from lidar_outliers.cloud import Cloud
from lidar_outliers.detectors.base import Detector


def reach(cloud: Cloud, params: DrorParameters, where: np.ndarray,
          allowed: np.ndarray | None = None) -> np.ndarray:
    """Each point's search radius (metres; every point is queried)."""
    from algorithms.dror import dynamic_radius

    radius = dynamic_radius(
        cloud.xyz, cloud.local_point(params.origin), multiplier=params.multiplier,
        angular_resolution=params.angular_resolution, min_radius=params.min_radius,
    )
    return radius


def run(cloud: Cloud, params: DrorParameters) -> DetectorResult:
    from algorithms.dror import detect_dror

    return detect_dror(
        cloud.xyz, origin=cloud.local_point(params.origin), multiplier=params.multiplier,
        angular_resolution=params.angular_resolution, min_radius=params.min_radius,
        k_min=params.k_min,
    )


DETECTOR = Detector(
    name="dror",
    parameters=DrorParameters,
    run=run,
    summary="Baseline (Charron et al. 2018): too few neighbours in a range-scaled sphere.",
    flag_bit=8,
    halo=lambda params: max(params.min_radius, 1.0),  # a first guess: radii grow with range
    reach=reach,
)
