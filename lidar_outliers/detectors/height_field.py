"""``height_field``: leave-one-out local height fields with edge-aware half patches and a robust
sigma (:mod:`algorithms.height_field`)."""

from __future__ import annotations

from algorithms.height_field import HeightFieldParameters
from algorithms.result import DetectorResult
from lidar_outliers.cloud import Cloud
from lidar_outliers.detectors.base import Detector, knn_reach


def run(cloud: Cloud, params: HeightFieldParameters) -> DetectorResult:
    from algorithms.height_field import detect_height_field

    return detect_height_field(cloud.xyz, **params.as_dict())


DETECTOR = Detector(
    name="height_field",
    parameters=HeightFieldParameters,
    run=run,
    summary="Leave-one-out local height fields with edge-aware half patches and robust sigma.",
    flag_bit=64,
    # k nearest neighbours besides the point; sigma "auto" is estimated from the whole cloud
    halo=lambda params: None if params.sigma == "auto" else 2.0,
    reach=lambda cloud, params: knn_reach(cloud.xyz, params.k + 1),
)
