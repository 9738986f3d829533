"""``patch``: the paper's quadric (eqs. 18-31) fitted to each point's k nearest neighbours, the
point tested with eq. 31 (algorithm (b); :mod:`algorithms.patch`)."""

from __future__ import annotations

from algorithms.patch import PatchParameters
from algorithms.result import DetectorResult
from lidar_outliers.cloud import Cloud
from lidar_outliers.detectors.base import Detector, knn_reach


def run(cloud: Cloud, params: PatchParameters) -> DetectorResult:
    from algorithms.patch import detect_patch

    return detect_patch(cloud.xyz, k=params.k, sigma=params.sigma, alpha=params.alpha)


DETECTOR = Detector(
    name="patch",
    parameters=PatchParameters,
    run=run,
    summary="Quadric fitted to each point's k nearest neighbours, tested with eq. 31.",
    flag_bit=2,
    # k nearest neighbours: a first guess, widened where a tile's patches reach further
    halo=lambda params: 2.0,
    reach=lambda cloud, params, where, allowed: knn_reach(cloud.xyz, params.k, where, allowed),
)
