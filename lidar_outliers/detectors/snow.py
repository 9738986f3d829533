"""``snow``: for spinning sensors, dark points with too few neighbours in a range-scaled sphere
(:mod:`algorithms.snow`)."""

from __future__ import annotations

import numpy as np

from algorithms.result import DetectorResult
from algorithms.snow import SnowParameters
from lidar_outliers.cloud import Cloud
from lidar_outliers.detectors.base import Detector
from lidar_outliers.errors import MissingDimensionError


def reach(cloud: Cloud, params: SnowParameters, where: np.ndarray,
          allowed: np.ndarray | None = None) -> np.ndarray:
    """Each point's search radius (metres; only the dark points are queried)."""
    from algorithms.dror import dynamic_radius

    radius = dynamic_radius(
        cloud.xyz, cloud.local_point(params.origin), multiplier=params.multiplier,
        angular_resolution=params.angular_resolution, min_radius=params.min_radius,
    )
    if cloud.intensity is None:
        return radius
    return np.where(cloud.intensity <= params.max_intensity, radius, 0.0)


def run(cloud: Cloud, params: SnowParameters) -> DetectorResult:
    from algorithms.snow import detect_snow

    if cloud.intensity is None:
        raise MissingDimensionError("the snow detector needs the points' intensity, which was "
                                    "not read from this file")
    return detect_snow(
        cloud.xyz, cloud.intensity, origin=cloud.local_point(params.origin),
        multiplier=params.multiplier, angular_resolution=params.angular_resolution,
        min_radius=params.min_radius, k_min=params.k_min, max_intensity=params.max_intensity,
    )


DETECTOR = Detector(
    name="snow",
    parameters=SnowParameters,
    run=run,
    summary="Spinning sensors: dark points with too few neighbours in a range-scaled sphere.",
    flag_bit=16,
    halo=lambda params: max(params.min_radius, 1.0),  # a first guess: radii grow with range
    reach=reach,
    needs=("intensity",),
)
