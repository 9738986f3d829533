"""``height_field``: leave-one-out local height fields with edge-aware half patches and a robust
sigma (:mod:`algorithms.height_field`).

It runs tile by tile: ``sigma: auto`` and the low test's horizontal spacing and voxel size are
measured over the whole cloud first (:class:`~lidar_outliers.detectors.base.Estimate`: sigma
and the spacing in one round, from the same sample, then the voxel size), the low test's grids
start at the file's lower-left corner in a tile as in the whole cloud, and each point reports
how far its result reached (:func:`algorithms.height_field.tile_reach`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from algorithms.height_field import HeightFieldParameters
from algorithms.result import DetectorResult
from lidar_outliers.cloud import Cloud
from lidar_outliers.detectors.base import Detector, Estimate
from lidar_outliers.detectors.detached import LADDER, grid_origin


def run(cloud: Cloud, params: HeightFieldParameters) -> DetectorResult:
    from algorithms.height_field import detect_height_field

    return detect_height_field(cloud.xyz, **params.as_dict(), origin=grid_origin(cloud),
                               wanted=cloud.wanted, sample=sigma_points(cloud),
                               sigma_floor=float(cloud.rounding_sigma().max()),
                               gps_time=cloud.gps_time)


def sigma_points(cloud: Cloud) -> np.ndarray:
    """(n,) bool: the points of the file ``sigma: auto`` and ``spacing_xy: auto`` are
    estimated from (:func:`algorithms.height_field.sigma_sample`, by position in the file)."""
    from algorithms.height_field import sigma_sample

    return sigma_sample(cloud.positions(), cloud.points_in_file())


def reach(cloud: Cloud, params: HeightFieldParameters, where: np.ndarray,
          allowed: np.ndarray | None = None) -> np.ndarray:
    from algorithms.height_field import LOW_PIECE_POINTS, pending_estimate, tile_reach

    if pending_estimate(params) == "voxel":
        return np.where(where, LADDER(cloud, LOW_PIECE_POINTS, float(params.spacing_xy))[1],
                        0.0)
    if pending_estimate(params) in ("sigma", "spacing_xy"):  # only the sample's are computed
        where = where & sigma_points(cloud)
    return tile_reach(cloud.xyz, params, where, grid_origin(cloud), allowed)


def values(cloud: Cloud, params: HeightFieldParameters) -> np.ndarray:
    from algorithms.height_field import LOW_PIECE_POINTS, estimate_values, pending_estimate

    if pending_estimate(params) == "voxel":
        return LADDER(cloud, LOW_PIECE_POINTS, float(params.spacing_xy))[0]
    wanted = cloud.wanted
    if pending_estimate(params) in ("sigma", "spacing_xy"):  # the sample's values alone
        sample = sigma_points(cloud)
        wanted = sample if wanted is None else wanted & sample
    return estimate_values(cloud.xyz, params, grid_origin(cloud), wanted)


def pin(params: HeightFieldParameters,
        parts: list[np.ndarray]) -> tuple[HeightFieldParameters, dict[str, Any]]:
    """``sigma: auto`` from every point's full-patch residual, as the whole-cloud run makes it
    (with the low test's spacing from the same round when that is "auto" too); then the low
    test's spacing and voxel size."""
    from dataclasses import replace

    from algorithms.detached import xy_spacing_of_values
    from algorithms.height_field import (
        pending_estimate,
        pin_low_estimate,
        sigma_of_residuals,
        spacing_with_sigma,
    )

    if pending_estimate(params) != "sigma":
        return pin_low_estimate(params, parts)
    both = spacing_with_sigma(params)  # (n, 2): residuals, XY distances
    sigma = sigma_of_residuals([p[:, 0] for p in parts] if both else parts)
    if not sigma > 0:  # as detect_height_field: a perfect surface leaves rounding only
        sigma = float(np.finfo(float).eps)
    pinned = replace(params, sigma=sigma)
    if both:
        pinned = replace(pinned, spacing_xy=xy_spacing_of_values([p[:, 1] for p in parts]))
    return pinned, {"sigma": sigma, "sigma_source": "auto"}


def pending(params: HeightFieldParameters) -> bool:
    from algorithms.height_field import pending_estimate

    return pending_estimate(params) is not None


DETECTOR = Detector(
    name="height_field",
    parameters=HeightFieldParameters,
    run=run,
    summary=("Leave-one-out local height fields with edge-aware half patches and robust sigma; "
             "clumps under the lowest ground-like surface (mirror returns)."),
    flag_bit=64,
    # k nearest neighbours besides the point: a first guess (the reach widens it, and the low
    # test's pieces and floors reach further)
    halo=lambda params: 2.0,
    reach=reach,
    estimate=Estimate(applies=pending, values=values, pin=pin),
)
