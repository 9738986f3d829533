"""``detached``: for airborne clouds, returns detached from the surface: small clusters under or
over its height envelope, pieces under the lowest surface, lone pits
(:mod:`algorithms.detached`)."""

from __future__ import annotations

from algorithms.detached import DetachedParameters
from algorithms.result import DetectorResult
from lidar_outliers.cloud import Cloud
from lidar_outliers.detectors.base import Detector


def run(cloud: Cloud, params: DetachedParameters) -> DetectorResult:
    from algorithms.detached import detect_detached

    return detect_detached(cloud.xyz, **params.as_dict())


DETECTOR = Detector(
    name="detached",
    parameters=DetachedParameters,
    run=run,
    summary="Airborne: returns detached from the surface (small clusters over or under it, "
    "pieces under the lowest surface, lone pits).",
    flag_bit=32,
)
