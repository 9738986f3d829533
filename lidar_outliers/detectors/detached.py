"""``detached``: for airborne clouds, small clusters under or over the local surface's height
envelope (:mod:`algorithms.detached`)."""

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
    summary="Airborne: small clusters under or over the local surface's height envelope.",
    flag_bit=32,
)
