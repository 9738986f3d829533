"""Dynamic-radius outlier removal (DROR, Charron, Phillips & Waslander 2018), the snow baseline.

A spinning LiDAR's points thin out with range: two neighbours on one ring are about
``range x angular_resolution`` apart. DROR therefore counts each point's neighbours inside a sphere
whose radius grows with the point's range from the sensor,

    radius_i = max(min_radius, multiplier x range_i x angular_resolution)

and calls the point noise when fewer than ``k_min`` other points fall inside. Falling snow is
sparse (one flake, one return), real surfaces are not. The defaults (multiplier 4, angular
resolution 0.2 degrees, k_min 2) are the setting reported best on the WADS frames (F1 0.85).

Not one of the paper's detectors (Leslar, Wang & Hu 2010 have no equation for it); it is the
baseline the new detectors are compared against.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from algorithms.checks import check_xyz
from algorithms.params import Parameters, param
from algorithms.result import DetectorResult

ORIGIN_DOC = ("Sensor position in the file's coordinates (0, 0, 0 for a cloud stored in the "
              "sensor frame, as spinning-sensor frames are).")
MULTIPLIER_DOC = "Radius = multiplier x range x angular_resolution (at least min_radius)."


@dataclass(frozen=True)
class DrorParameters(Parameters):
    """Baseline: dynamic-radius outlier removal (Charron et al. 2018) for spinning sensors."""

    multiplier: float = param(4.0, MULTIPLIER_DOC, gt=0, le=100)
    angular_resolution: float = param(
        0.2, "Sensor's horizontal angular step in degrees.", gt=0, le=10)
    min_radius: float = param(0.04, "Least search radius, metres.", ge=0, le=100)
    k_min: int = param(2, "Fewer other points than this in the sphere: noise.", ge=1, le=1000)
    origin: tuple[float, float, float] = param((0.0, 0.0, 0.0), ORIGIN_DOC)


def dynamic_radius(
    xyz: np.ndarray,
    origin: np.ndarray | tuple[float, float, float] = (0.0, 0.0, 0.0),
    *,
    multiplier: float = 4.0,
    angular_resolution: float = 0.2,
    min_radius: float = 0.04,
) -> np.ndarray:
    """Search radius per point: max(min_radius, multiplier x range x angular_resolution).

    xyz : (n, 3) float64, metres, in the same frame as ``origin``.
    origin : (3,) sensor position (the sensor frame's origin for a spinning sensor's frame).
    angular_resolution : degrees (the sensor's horizontal step between two firings).
    Returns (n,) float64 radii in metres.
    """
    if not multiplier > 0 or not angular_resolution > 0 or not min_radius >= 0:
        raise ValueError("multiplier and angular_resolution must be > 0, min_radius >= 0")
    rng = np.linalg.norm(xyz - np.asarray(origin, dtype=np.float64), axis=1)
    return np.maximum(min_radius, multiplier * rng * np.deg2rad(angular_resolution))


def neighbour_counts(
    xyz: np.ndarray, radius: np.ndarray, cap: int, *, queries: np.ndarray | None = None,
) -> np.ndarray:
    """Number of OTHER points within ``radius[i]`` (inclusive) of each queried point, up to ``cap``.

    xyz : (n, 3) float64, the whole cloud; radius : (q,) float64, one radius per queried point.
    queries : (q,) indices of the queried points (default: every point).
    Returns (q,) int64 in [0, cap]. A duplicate of a point counts as a neighbour.

    DROR needs only "at least k_min or not", so the count stops at ``cap``: the (cap + 1)
    nearest points (the point itself among them) are read instead of every point in the sphere.
    Far from the origin the spheres hold thousands of points; the capped count does not grow
    with them.
    """
    queries = np.arange(len(xyz)) if queries is None else np.asarray(queries)
    if len(queries) == 0:
        return np.zeros(0, dtype=np.int64)
    from algorithms.neighbours import neighbour_tree, query_nearest

    dist, _ = query_nearest(neighbour_tree(xyz), xyz[queries], cap + 1)
    dist = dist.reshape(len(queries), cap + 1)
    inside = dist <= np.asarray(radius, dtype=np.float64)[:, None]
    return np.count_nonzero(inside, axis=1).astype(np.int64) - 1  # the point itself


def detect_dror(
    xyz: np.ndarray,
    *,
    origin: np.ndarray | tuple[float, float, float] = (0.0, 0.0, 0.0),
    multiplier: float = 4.0,
    angular_resolution: float = 0.2,
    min_radius: float = 0.04,
    k_min: int = 2,
) -> DetectorResult:
    """DROR: flag the points with fewer than ``k_min`` neighbours in their dynamic radius.

    xyz : (n, 3) float64 metres, in the frame of ``origin`` (the sensor position).
    Returns a DetectorResult whose score is ``k_min - neighbours``, the neighbours missing to
    be kept (0 for every point with at least ``k_min``; critical value 0: flagged when score > 0).

    >>> pts = np.array([[10.0, 0, 0], [10.0, 0.01, 0], [10.0, 0.02, 0], [5.0, 5.0, 5.0]])
    >>> detect_dror(pts).flagged.tolist()
    [False, False, False, True]
    """
    DrorParameters(multiplier=multiplier, angular_resolution=angular_resolution,
                   min_radius=min_radius, k_min=k_min, origin=tuple(np.asarray(origin).tolist()))
    xyz = check_xyz(xyz)
    radius = dynamic_radius(
        xyz, origin, multiplier=multiplier, angular_resolution=angular_resolution,
        min_radius=min_radius,
    )
    counts = neighbour_counts(xyz, radius, k_min)
    score = (k_min - counts).astype(np.float64)
    flagged = score > 0
    info = {
        "k_min": int(k_min), "multiplier": float(multiplier),
        "angular_resolution": float(angular_resolution), "min_radius": float(min_radius),
        "origin": [float(v) for v in np.asarray(origin, dtype=np.float64)],
        "points_tested": int(len(xyz)), "points_flagged": int(flagged.sum()),
    }
    return DetectorResult(score=score, flagged=flagged, critical_value=0.0, info=info)
