"""The points as plain arrays: what the detectors see of a LAS/LAZ file."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from algorithms.columns import column_max, column_min
from lidar_outliers.errors import MissingDimensionError, ParameterError


@dataclass
class Cloud:
    """The points as plain arrays, in file order.

    Attributes
    ----------
    xyz : (n, 3) float64
        Coordinates in metres relative to ``origin`` (world = xyz + origin).
    origin : (3,) float64
        Local origin, a point of the file's integer grid near the centre of the bounds.
    gps_time : (n,) float64 or None
        GPS time in seconds; None for point formats without it.
    point_source_id, classification : (n,) integer arrays
    intensity : (n,) uint16 or None
        Pulse return strength (the ``snow`` detector uses it); None when not read.
    trajectory : (m, 4) float64 or None
        Optional platform path (:mod:`~lidar_outliers.trajectory`): time, then x, y, z in the
        same local frame as ``xyz`` (file coordinates minus ``origin``); the ``transient``
        detector adds free-space evidence with it. A subset keeps the whole trajectory.
    anchor : (2,) float64 or None
        Lower-left XY corner of the whole file in the local frame, where grids of square cells
        (``section``) start; None: the corner of the points at hand. A subset and a tile keep
        it, so their cells are the whole cloud's.
    known : dict of (n,) structured arrays, or None
        Per detector, what a pass over the whole file gave each point (its ``index`` in the
        file among it) when the cloud is a tile's region
        (:class:`~lidar_outliers.detectors.base.Prepass`); None: the cloud is all there is. A
        subset keeps its points' rows.
    wanted : (n,) bool or None
        The points whose results are read, when that is not all of them (a tile's core):
        detectors that can may leave the others untested. A subset keeps its points' rows.
    position : (n,) int64 or None
        Each point's position in the file (None: its row, the cloud being the file in order);
        a subset and a tile keep them, so a sample of the file drawn by position is the same
        in every part of it.
    file_points : int or None
        Points in the file (None: this cloud's), kept by a subset.
    scales : (3,) float64 or None
        The file's coordinate resolution (the LAS header's scales; None: not known): no
        estimate of the noise goes below its rounding (``sigma: auto``).
    """

    xyz: np.ndarray
    origin: np.ndarray
    gps_time: np.ndarray | None
    point_source_id: np.ndarray
    classification: np.ndarray
    intensity: np.ndarray | None = None
    trajectory: np.ndarray | None = None
    anchor: np.ndarray | None = None
    known: dict[str, np.ndarray] | None = None
    wanted: np.ndarray | None = None
    position: np.ndarray | None = None
    file_points: int | None = None
    scales: np.ndarray | None = None

    @classmethod
    def from_arrays(
        cls,
        xyz: np.ndarray,
        *,
        gps_time: np.ndarray | None = None,
        point_source_id: np.ndarray | None = None,
        intensity: np.ndarray | None = None,
        classification: np.ndarray | None = None,
    ) -> Cloud:
        """A cloud from world coordinates (n, 3): the origin is a point near their centre, so
        coordinates near 5,000,000 m keep their precision. Missing ids and classes are 0."""
        world = np.asarray(xyz, dtype=np.float64)
        if world.ndim != 2 or world.shape[1] != 3:
            raise ParameterError(f"xyz must have shape (n, 3), got {world.shape}")
        n = world.shape[0]
        origin = np.round((column_min(world) + column_max(world)) / 2) if n else np.zeros(3)

        def column(values: np.ndarray | None, dtype: type, name: str) -> np.ndarray:
            if values is None:
                return np.zeros(n, dtype=dtype)
            arr = np.asarray(values)
            if arr.shape != (n,):
                raise ParameterError(f"{name} must have shape ({n},), got {arr.shape}")
            return arr.astype(dtype, copy=False)

        return cls(
            xyz=world - origin, origin=origin,
            gps_time=None if gps_time is None else column(gps_time, np.float64, "gps_time"),
            point_source_id=column(point_source_id, np.uint16, "point_source_id"),
            classification=column(classification, np.uint8, "classification"),
            intensity=None if intensity is None else column(intensity, np.uint16, "intensity"),
        )

    def __len__(self) -> int:
        return int(self.xyz.shape[0])

    def subset(self, index: np.ndarray) -> Cloud:
        """The points at ``index`` (integer indices or a boolean mask), same origin."""
        return Cloud(
            xyz=self.xyz[index],
            origin=self.origin,
            gps_time=None if self.gps_time is None else self.gps_time[index],
            point_source_id=self.point_source_id[index],
            classification=self.classification[index],
            intensity=None if self.intensity is None else self.intensity[index],
            trajectory=self.trajectory,
            anchor=self.anchor,
            known=None if self.known is None else {k: v[index] for k, v in self.known.items()},
            wanted=None if self.wanted is None else self.wanted[index],
            position=self.positions()[index], file_points=self.points_in_file(),
            scales=self.scales,
        )

    def rounding_sigma(self) -> np.ndarray:
        """(3,) the standard deviation of the coordinates' rounding to ``scales`` (zeros when
        not known): the least noise any estimate may give."""
        from algorithms.stats import rounding_sigma

        return rounding_sigma(self.scales)

    def positions(self) -> np.ndarray:
        """(n,) each point's position in the file."""
        return np.arange(len(self)) if self.position is None else self.position

    def points_in_file(self) -> int:
        """The number of points in the file the cloud comes from."""
        return len(self) if self.file_points is None else self.file_points

    def with_trajectory(self, trajectory: np.ndarray) -> Cloud:
        """The same points with ``trajectory`` ((m, 4): time, then x, y, z in file coordinates)
        moved into the cloud's local frame."""
        return replace(self, trajectory=trajectory - np.r_[0.0, self.origin])

    def require_gps_time(self, detector: str) -> np.ndarray:
        """The GPS times, or MissingDimensionError naming the detector that needs them."""
        if self.gps_time is None:
            raise MissingDimensionError(
                f"the {detector} detector needs gps_time, which this point format does not have "
                f"(use point format 1, 3-10, or run patch/section instead)"
            )
        return self.gps_time

    def local_point(self, point: tuple[float, float, float]) -> np.ndarray:
        """A point given in file coordinates (a sensor position, say) in the local frame."""
        return np.asarray(point, dtype=np.float64) - np.asarray(self.origin, dtype=np.float64)
