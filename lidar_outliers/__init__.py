"""lidar-outliers: find outliers in LiDAR point clouds.

The library in a few names::

    import lidar_outliers as lo

    cloud = lo.read_cloud("scan.las")                      # LAS/LAZ -> plain arrays
    result = lo.detect(cloud, {"pipeline": [{"detector": "temporal", "sigma": 0.01}]})
    result.flags, result.scores["temporal"], result.statistics
    lo.process_file("scan.las", "flagged.laz")             # file to file, as the command line
    lo.DETECTORS["patch"].parameters()                     # every detector, its parameters

:func:`detect` runs a pipeline on points in memory (a :class:`Cloud`, or an (n, 3) array);
:func:`process_file` reads, detects and writes the flagged cloud with every original
dimension, VLR and EVLR kept. Parameters are validated by the same models as the command line
and the web service (:class:`PipelineParams`, one model per detector in :data:`DETECTORS`).
Every error a user can cause derives from :class:`LidarOutliersError`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from lidar_outliers.cloud import Cloud
from lidar_outliers.detectors import DETECTORS, FLAG_BITS, Detector, get_detector
from lidar_outliers.errors import (
    LasFormatError,
    LidarOutliersError,
    MissingDimensionError,
    ParameterError,
)
from lidar_outliers.lasio import inspect_las, read_cloud
from lidar_outliers.params import PipelineParams, parse_pipeline_params, stage
from lidar_outliers.pipeline import PipelineResult, run_pipeline
from lidar_outliers.process import process_file

__all__ = [
    "DETECTORS", "FLAG_BITS", "Cloud", "Detector", "LasFormatError", "LidarOutliersError",
    "MissingDimensionError", "ParameterError", "PipelineParams", "PipelineResult", "detect",
    "get_detector", "inspect_las", "parse_pipeline_params", "process_file", "read_cloud",
    "stage",
]


def detect(
    points: Cloud | np.ndarray,
    params: PipelineParams | dict[str, Any] | str | None = None,
    *,
    gps_time: np.ndarray | None = None,
    point_source_id: np.ndarray | None = None,
    intensity: np.ndarray | None = None,
    classification: np.ndarray | None = None,
) -> PipelineResult:
    """Run a pipeline of detectors on points in memory.

    ``points``: a :class:`Cloud` (from :func:`read_cloud`), or (n, 3) coordinates in metres with
    the optional per-point arrays as keywords. ``params``: a pipeline document (dict or JSON
    text, as ``lidar-outliers detect --params`` takes) or :class:`PipelineParams`; None runs the
    default pipeline of the points' profile. Returns the flags (uint16 ``outlier_flags``), the
    scores per detector (NaN where untested), the new classes and the statistics.
    """
    cloud = points if isinstance(points, Cloud) else Cloud.from_arrays(
        points, gps_time=gps_time, point_source_id=point_source_id, intensity=intensity,
        classification=classification)
    if params is None:
        params = PipelineParams()
    elif not isinstance(params, PipelineParams):
        params = parse_pipeline_params(params)
    return run_pipeline(cloud, params)
