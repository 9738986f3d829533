"""``snow``: for spinning sensors, dark points with too few neighbours in a range-scaled sphere
(:mod:`algorithms.snow`)."""

from __future__ import annotations

from algorithms.result import DetectorResult
from algorithms.snow import SnowParameters
from lidar_outliers.cloud import Cloud
from lidar_outliers.detectors.base import Detector
from lidar_outliers.errors import MissingDimensionError


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
    needs=("intensity",),
)
