"""``height_field``: leave-one-out local height fields with edge-aware half patches and a robust
sigma (:mod:`algorithms.height_field`)."""

from __future__ import annotations

from typing import Any

import numpy as np

from algorithms.height_field import HeightFieldParameters
from algorithms.result import DetectorResult
from lidar_outliers.cloud import Cloud
from lidar_outliers.detectors.base import Detector, Estimate, knn_reach


def run(cloud: Cloud, params: HeightFieldParameters) -> DetectorResult:
    from algorithms.height_field import detect_height_field

    return detect_height_field(cloud.xyz, **params.as_dict())


def residuals(cloud: Cloud, params: HeightFieldParameters) -> np.ndarray:
    from algorithms.height_field import full_residuals

    return full_residuals(cloud.xyz, params.k)


def pin_sigma(
    params: HeightFieldParameters, parts: list[np.ndarray]
) -> tuple[HeightFieldParameters, dict[str, Any]]:
    """``sigma: auto`` from every point's full-patch residual, as the whole-cloud run makes it."""
    from dataclasses import replace

    from algorithms.height_field import sigma_of_residuals

    sigma = sigma_of_residuals(parts)
    if not sigma > 0:  # as detect_height_field: a perfect surface leaves rounding only
        sigma = float(np.finfo(float).eps)
    return replace(params, sigma=sigma), {"sigma": sigma, "sigma_source": "auto"}


DETECTOR = Detector(
    name="height_field",
    parameters=HeightFieldParameters,
    run=run,
    summary=("Leave-one-out local height fields with edge-aware half patches and robust sigma; "
             "clumps under the lowest ground-like surface (mirror returns)."),
    flag_bit=64,
    # k nearest neighbours besides the point; sigma "auto" is estimated from every point's
    # residual first. The low test's pieces and voxel size are the whole cloud's: not in tiles
    halo=lambda params: None if params.low else 2.0,
    whole_cloud=("its low test (low: true, the default) cuts the cloud into pieces joined "
                 "through occupied voxels, at a voxel size found over the whole cloud; with "
                 "low: false it runs in tiles"),
    reach=lambda cloud, params, where: knn_reach(cloud.xyz, params.k + 1, where),
    estimate=Estimate(applies=lambda params: params.sigma == "auto", values=residuals,
                      pin=pin_sigma),
)
