"""``ground``: the iterative TIN ground filter (step-edge triangles by slope, adjust, repeat;
:mod:`algorithms.ground`). It classifies instead of flagging: class 2 or 1."""

from __future__ import annotations

import numpy as np

from algorithms.ground import GroundParameters
from lidar_outliers.cloud import Cloud
from lidar_outliers.detectors.base import Detector, GroundResult


def run(cloud: Cloud, params: GroundParameters) -> GroundResult:
    from algorithms.ground import classify_ground

    out = classify_ground(cloud.xyz, **params.as_dict())
    return GroundResult(is_ground=np.asarray(out.is_ground, dtype=bool), info=dict(out.info))


DETECTOR = Detector(
    name="ground",
    parameters=GroundParameters,
    run=run,
    summary="Iterative TIN ground filter: class 2 (ground) or 1 for unflagged points.",
    kind="ground",
)
