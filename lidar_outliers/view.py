"""A decimated copy of a flagged cloud for a viewer: at most ``max_points`` points spread evenly in
space, every outlier kept, as float32 coordinates about a centre and the uint16 ``outlier_flags``.

The binary layout (little-endian), media type :data:`MEDIA_TYPE`::

    8 bytes      b"LOPOINTS"
    4 bytes      uint32 H: length of the JSON header (padded with spaces to a multiple of 4)
    H bytes      JSON {"points": n, "total": N, "outliers": k, "outliers_kept": k',
                       "centre": [x, y, z], "bits": {"temporal": 1, ...}}
    12 n bytes   float32 x, y, z of each point minus the centre, point after point
    2 n bytes    uint16 outlier_flags of each point

Both arrays start at multiples of their item size, so a browser reads them as typed arrays
without copying. Points are in file order.
"""

from __future__ import annotations

import json
import os
import struct
from dataclasses import dataclass
from typing import Any

import numpy as np

from algorithms.columns import column_max, column_min
from lidar_outliers import lasio
from lidar_outliers.detectors import FLAG_BITS
from lidar_outliers.output import FLAGS_DIMENSION, FLAGS_DTYPE

MAGIC = b"LOPOINTS"
MEDIA_TYPE = "application/vnd.lidar-outliers.points"
DEFAULT_MAX_POINTS = 200_000
#: Bits per axis of the octree codes: 3 x 21 bits fill a uint64.
_LEVELS = 21


@dataclass
class ViewPoints:
    """What a viewer draws: ``xyz`` (n, 3) float32 about ``centre`` (world coordinates) and
    ``flags`` (n,) uint16, taken from a cloud of ``total`` points of which ``outliers`` are
    flagged."""

    xyz: np.ndarray
    flags: np.ndarray
    centre: np.ndarray
    total: int
    outliers: int

    def header(self) -> dict[str, Any]:
        return {"points": len(self.flags), "total": self.total, "outliers": self.outliers,
                "outliers_kept": int(np.count_nonzero(self.flags)),
                "centre": [float(c) for c in self.centre], "bits": dict(FLAG_BITS)}

    def subset(self, index: np.ndarray) -> ViewPoints:
        return ViewPoints(self.xyz[index], self.flags[index], self.centre, self.total,
                          self.outliers)

    def to_bytes(self) -> bytes:
        """The binary layout above."""
        text = json.dumps(self.header(), separators=(",", ":")).encode()
        text += b" " * (-len(text) % 4)
        return b"".join([
            MAGIC, struct.pack("<I", len(text)), text,
            np.ascontiguousarray(self.xyz, dtype="<f4").tobytes(),
            np.ascontiguousarray(self.flags, dtype="<u2").tobytes(),
        ])


def parse(data: bytes) -> tuple[dict[str, Any], np.ndarray, np.ndarray]:
    """The header, xyz (n, 3) float32 and flags (n,) uint16 of :meth:`ViewPoints.to_bytes`."""
    if data[:8] != MAGIC:
        raise ValueError("not a points file: wrong magic bytes")
    (size,) = struct.unpack("<I", data[8:12])
    header = json.loads(data[12:12 + size])
    n = int(header["points"])
    start = 12 + size
    xyz = np.frombuffer(data, dtype="<f4", count=3 * n, offset=start).reshape(n, 3)
    flags = np.frombuffer(data, dtype="<u2", count=n, offset=start + 12 * n)
    return header, xyz, flags


def read_view_points(path: str | os.PathLike[str]) -> ViewPoints:
    """Every point of a result file as float32 about its centre, with its flags (zeros when the
    file has no ``outlier_flags``); 14 bytes a point, read chunk by chunk."""
    import laspy

    with laspy.open(path) as reader:
        header = reader.header
    n = int(header.point_count)
    grid, centre = lasio.grid_origin(header)
    scales = np.asarray(header.scales)
    has_flags = FLAGS_DIMENSION in header.point_format.extra_dimension_names
    xyz = np.empty((n, 3), dtype=np.float32)
    flags = np.zeros(n, dtype=FLAGS_DTYPE)
    start = 0
    for chunk in lasio.iter_chunks(path):
        stop = start + len(chunk)
        xyz[start:stop] = lasio.local_xyz(chunk, grid, scales)
        if has_flags:
            flags[start:stop] = chunk.array[FLAGS_DIMENSION]
        start = stop
    return ViewPoints(xyz, flags, centre, n, int(np.count_nonzero(flags)))


def decimate(xyz: np.ndarray, flags: np.ndarray, max_points: int, seed: int = 0) -> np.ndarray:
    """Sorted indices of at most ``max_points`` points: every flagged point (a random subset of
    them when they alone exceed the budget) and the unflagged ones spread evenly in space."""
    if max_points < 1:
        raise ValueError(f"max_points must be at least 1, got {max_points}")
    n = len(flags)
    if n <= max_points:
        return np.arange(n)
    rng = np.random.default_rng(seed)
    outliers = np.flatnonzero(flags != 0)
    if outliers.size >= max_points:
        return np.sort(rng.choice(outliers, max_points, replace=False))
    inliers = np.flatnonzero(flags == 0)
    kept = inliers[spread_evenly(xyz[inliers], max_points - outliers.size, rng)]
    return np.sort(np.concatenate([outliers, kept]))


def spread_evenly(xyz: np.ndarray, budget: int, rng: np.random.Generator) -> np.ndarray:
    """Indices of at most ``budget`` points spread evenly in space.

    One random point per occupied cube of the finest octree level that has at least ``budget``
    occupied cubes, thinned at random to ``budget``. Dense parts thus lose more points than
    sparse ones, unlike a plain random sample, which keeps the density of the scan.
    """
    n = len(xyz)
    if n <= budget:
        return np.arange(n)
    lo = column_min(xyz).astype(np.float64)
    extent = max(float((column_max(xyz) - lo).max()), 1e-9)
    cells = ((xyz - lo) * ((2**_LEVELS - 1) / extent)).astype(np.uint64)
    code = _spread_bits(cells[:, 0]) | (_spread_bits(cells[:, 1]) << 1) | (
        _spread_bits(cells[:, 2]) << 2)
    # shuffled first, then a stable sort: the first point of each cube is a random one of it
    order = rng.permutation(n)
    order = order[np.argsort(code[order], kind="stable")]
    code = code[order]
    starts = np.zeros(0, dtype=np.int64)
    for level in range(1, _LEVELS + 1):
        keys = code >> np.uint64(3 * (_LEVELS - level))
        starts = np.flatnonzero(np.r_[True, keys[1:] != keys[:-1]])
        if starts.size >= budget:
            break
    chosen = order[starts]
    if chosen.size > budget:
        chosen = rng.choice(chosen, budget, replace=False)
    return chosen


def _spread_bits(v: np.ndarray) -> np.ndarray:
    """Put two zero bits after each of the low 21 bits of ``v`` (uint64): the octree code."""
    v = v & np.uint64(0x1FFFFF)
    v = (v | (v << np.uint64(32))) & np.uint64(0x1F00000000FFFF)
    v = (v | (v << np.uint64(16))) & np.uint64(0x1F0000FF0000FF)
    v = (v | (v << np.uint64(8))) & np.uint64(0x100F00F00F00F00F)
    v = (v | (v << np.uint64(4))) & np.uint64(0x10C30C30C30C30C3)
    v = (v | (v << np.uint64(2))) & np.uint64(0x1249249249249249)
    return v


def view_points(path: str | os.PathLike[str], max_points: int = DEFAULT_MAX_POINTS) -> bytes:
    """The binary layout above for a result file."""
    cloud = read_view_points(path)
    index = decimate(cloud.xyz, cloud.flags, max_points)
    return (cloud.subset(index) if index.size < cloud.total else cloud).to_bytes()
