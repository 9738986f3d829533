"""``detached``: for airborne clouds, returns detached from the surface: small clusters under or
over its height envelope, pieces under the lowest surface, lone pits
(:mod:`algorithms.detached`).

It runs tile by tile: the cloud's spacings and voxel size are measured over the whole cloud
first (:class:`~lidar_outliers.detectors.base.Estimate`, one round each), every grid starts at
the file's lower-left corner (the cloud's ``anchor``) in a tile as in the whole cloud, and each
point reports how far its result reached (:func:`algorithms.detached.tile_reach`), so a tile
whose clusters, pieces or floors cross its halo runs again with a wider one.
"""

from __future__ import annotations

import hashlib
from typing import Any

import numpy as np

from algorithms.detached import DetachedParameters
from algorithms.result import DetectorResult
from lidar_outliers.cloud import Cloud
from lidar_outliers.detectors.base import Detector, Estimate


def grid_origin(cloud: Cloud) -> np.ndarray | None:
    """(3,) the corner of the detector's grids: the file's lower-left corner, shared by the
    whole cloud, its subsets and its tiles (None: the cloud's own lowest corner)."""
    return None if cloud.anchor is None else np.r_[cloud.anchor, 0.0]


class LadderMemo:
    """The small-piece ladder (:func:`algorithms.detached.ladder_pieces`: bits and reach) of
    the last cloud asked for. A tile's reach check and then its values of the voxel estimate
    cut the same points at every voxel size; with the memo they are cut once."""

    def __init__(self) -> None:
        self.key: tuple[Any, ...] | None = None
        self.value: tuple[np.ndarray, np.ndarray] | None = None

    def __call__(self, cloud: Cloud, piece_points: int,
                 start: float) -> tuple[np.ndarray, np.ndarray]:
        from algorithms.detached import ladder_pieces, relative

        xyz = np.ascontiguousarray(cloud.xyz)
        origin = grid_origin(cloud)
        key = (hashlib.blake2b(xyz.view(np.uint8), digest_size=16).digest(), xyz.shape,
               None if origin is None else origin.tobytes(), piece_points, start)
        if key != self.key or self.value is None:
            self.key, self.value = None, None  # a failed cut leaves no stale entry
            self.value = ladder_pieces(relative(xyz, origin), piece_points, start)
            self.key = key
        return self.value


#: One per process: the reach check and the values of a tile run one after the other.
LADDER = LadderMemo()


def run(cloud: Cloud, params: DetachedParameters) -> DetectorResult:
    from algorithms.detached import detect_detached

    return detect_detached(cloud.xyz, **params.as_dict(), origin=grid_origin(cloud))


def reach(cloud: Cloud, params: DetachedParameters, where: np.ndarray,
          allowed: np.ndarray | None = None) -> np.ndarray:
    from algorithms.detached import pending_estimate, tile_reach

    if pending_estimate(params) == "voxel":
        return np.where(where, LADDER(cloud, params.piece_points, float(params.spacing_xy))[1],
                        0.0)
    return tile_reach(cloud.xyz, params, where, grid_origin(cloud), allowed)


def values(cloud: Cloud, params: DetachedParameters) -> np.ndarray:
    from algorithms.detached import estimate_values, pending_estimate

    if pending_estimate(params) == "voxel":
        return LADDER(cloud, params.piece_points, float(params.spacing_xy))[0]
    return estimate_values(cloud.xyz, params, grid_origin(cloud), cloud.wanted)


def pin(params: DetachedParameters,
        parts: list[np.ndarray]) -> tuple[DetachedParameters, dict[str, Any]]:
    from algorithms.detached import pin_estimate

    return pin_estimate(params, parts)


def pending(params: DetachedParameters) -> bool:
    from algorithms.detached import pending_estimate

    return pending_estimate(params) is not None


DETECTOR = Detector(
    name="detached",
    parameters=DetachedParameters,
    run=run,
    summary="Airborne: returns detached from the surface (small clusters over or under it, "
    "pieces under the lowest surface, lone pits).",
    flag_bit=32,
    # a first guess: clusters join over a few links, floors span many cells (reach widens it)
    halo=lambda params: 2.0 * max(params.link, params.pit_radius, 1.0),
    reach=reach,
    estimate=Estimate(applies=pending, values=values, pin=pin),
)
