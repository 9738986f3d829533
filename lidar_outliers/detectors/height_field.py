"""``height_field``: leave-one-out local height fields with edge-aware half patches and a robust
sigma (:mod:`algorithms.height_field`).

It runs tile by tile: ``sigma: auto`` and the low test's horizontal spacing and voxel size are
measured over the whole cloud first (:class:`~lidar_outliers.detectors.base.Estimate`: in one
round, sigma and the spacing from the same sample and, from every point, the small-piece ladder
the voxel size is chosen from; with sigma given, the spacing and then the voxel size), the low
test's grids start at the file's lower-left corner in a tile as in the whole cloud, and each
point reports how far its result reached (:func:`algorithms.height_field.tile_reach`).
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

    pending = pending_estimate(params)
    if pending == "voxel":
        return np.where(where, LADDER(cloud, LOW_PIECE_POINTS, float(params.spacing_xy))[1],
                        0.0)
    if pending == "spacing_xy":  # only the sample's are computed
        where = where & sigma_points(cloud)
    if pending == "sigma":  # the sample's residuals and distances, every point's ladder
        return tile_reach(cloud.xyz, params, where, grid_origin(cloud), allowed,
                          sample=sigma_points(cloud), ladder=sigma_round_ladder(cloud, params))
    return tile_reach(cloud.xyz, params, where, grid_origin(cloud), allowed)


def sigma_round_ladder(cloud: Cloud, params: HeightFieldParameters
                       ) -> tuple[np.ndarray, np.ndarray] | None:
    """The ladder the round that estimates ``sigma`` cuts (:func:`algorithms.height_field.
    voxel_with_sigma`; None when it cuts none), cut once for a tile's reach check and values
    (:data:`~lidar_outliers.detectors.detached.LADDER`)."""
    from algorithms.height_field import LOW_PIECE_POINTS, SIGMA_ROUND_LADDER_START, voxel_with_sigma

    if not voxel_with_sigma(params):
        return None
    return LADDER(cloud, LOW_PIECE_POINTS, SIGMA_ROUND_LADDER_START)


def values(cloud: Cloud, params: HeightFieldParameters) -> np.ndarray:
    from algorithms.height_field import LOW_PIECE_POINTS, estimate_values, pending_estimate

    if pending_estimate(params) == "voxel":
        return LADDER(cloud, LOW_PIECE_POINTS, float(params.spacing_xy))[0]
    wanted = cloud.wanted
    if pending_estimate(params) in ("sigma", "spacing_xy"):  # the sample's values alone
        sample = sigma_points(cloud)
        wanted = sample if wanted is None else wanted & sample
    ladder = sigma_round_ladder(cloud, params)
    return estimate_values(cloud.xyz, params, grid_origin(cloud), wanted,
                           ladder=None if ladder is None else ladder[0])


def pin(params: HeightFieldParameters,
        parts: list[np.ndarray]) -> tuple[HeightFieldParameters, dict[str, Any]]:
    """``sigma: auto`` from every point's full-patch residual, as the whole-cloud run makes it,
    with the low test's spacing and voxel size from the same round when they are "auto" too
    (:func:`algorithms.height_field.pin_sigma_round`); else the low test's spacing, then its
    voxel size."""
    from algorithms.height_field import pending_estimate, pin_low_estimate, pin_sigma_round

    if pending_estimate(params) != "sigma":
        return pin_low_estimate(params, parts)
    return pin_sigma_round(params, parts)


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
    # k nearest neighbours besides the point and, for a scatter seen again, the lowest return
    # around it: a first guess (the reach widens it, and the low test's pieces and floors
    # reach further)
    halo=lambda params: 3.0 if params.static_dt > 0 or params.foliage_reach > 0 else 2.0,
    reach=reach,
    estimate=Estimate(applies=pending, values=values, pin=pin),
)
