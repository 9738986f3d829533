"""``temporal``: the paper's moving fixed-interval smoother along each scanner's time series
(algorithm (a), eqs. 1-17; :mod:`algorithms.temporal`)."""

from __future__ import annotations

from algorithms.result import DetectorResult
from algorithms.temporal import TemporalParameters
from lidar_outliers.cloud import Cloud
from lidar_outliers.detectors.base import Detector


def run(cloud: Cloud, params: TemporalParameters) -> DetectorResult:
    from algorithms.temporal import detect_temporal

    group = None if params.group_by == "none" else cloud.point_source_id
    return detect_temporal(
        cloud.xyz, cloud.require_gps_time("temporal"), group,
        n1=params.n1, n2=params.n2, sigma=params.sigma, alpha=params.alpha,
        max_gap=params.max_gap, sigma_floor=cloud.rounding_sigma(),
    )


DETECTOR = Detector(
    name="temporal",
    parameters=TemporalParameters,
    run=run,
    summary="Moving fixed-interval smoother along each scanner's time series (eqs. 1-17).",
    flag_bit=1,
    needs=("gps_time",),
    # each scanner's time series, no XY neighbourhood: streamed along time before any tiles
    streams=True,
    whole_cloud=("its scanners' time series cross every tile: in a tiled run it is streamed "
                 "along time, at the start of the pipeline only"),
)
