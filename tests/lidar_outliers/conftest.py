"""Synthetic LAS/LAZ files written with laspy for the worker and CLI tests."""

from __future__ import annotations

from pathlib import Path

import laspy
import numpy as np
import pytest
from laspy.vlrs.known import WktCoordinateSystemVlr

WKT = 'PROJCS["ETRS89 / UTM zone 32N",GEOGCS["ETRS89",DATUM["European_Terrestrial_Reference_' \
      'System_1989",SPHEROID["GRS 1980",6378137,298.257222101]]],UNIT["metre",1]]'

VERSION_FOR_FORMAT = {0: "1.2", 1: "1.2", 2: "1.2", 3: "1.2", 4: "1.3", 5: "1.3",
                      6: "1.4", 7: "1.4", 8: "1.4", 9: "1.4", 10: "1.4"}


def scan_line_cloud(n: int, rng: np.random.Generator, *, spikes: int = 0,
                    spike_size: float = 1.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A mobile-scanner-like cloud: smooth 3-D profiles along time, optional spikes.

    Returns xyz (n, 3) in metres near the origin, gps_time (n,) seconds from 0, and a bool mask of
    the spiked points.
    """
    t = np.arange(n) * 1e-4 + rng.uniform(0, 2e-5, n)
    phase = t * 50.0
    xyz = np.column_stack(
        [10 * np.cos(phase) + 2.0 * t, 10 * np.sin(phase), 0.5 * np.sin(3 * phase)]
    )
    xyz += rng.normal(0, 0.003, xyz.shape)
    spiked = np.zeros(n, dtype=bool)
    if spikes:
        idx = rng.choice(np.arange(20, n - 20), spikes, replace=False)
        xyz[idx, 2] += spike_size
        spiked[idx] = True
    return xyz, t, spiked


def write_las(
    path: Path,
    xyz: np.ndarray,
    *,
    gps_time: np.ndarray | None = None,
    point_format: int = 3,
    version: str | None = None,
    offsets: tuple[float, float, float] = (0.0, 0.0, 0.0),
    scales: tuple[float, float, float] = (0.001, 0.001, 0.001),
    classification: np.ndarray | None = None,
    point_source_id: np.ndarray | None = None,
    extra: dict[str, np.ndarray] | None = None,
    random_dims: bool = False,
    crs: bool = False,
    evlr: bool = False,
    seed: int = 0,
) -> Path:
    """Write a LAS/LAZ file (by suffix) with laspy; returns its path."""
    header = laspy.LasHeader(version=version or VERSION_FOR_FORMAT[point_format],
                             point_format=point_format)
    header.offsets = np.asarray(offsets)
    header.scales = np.asarray(scales)
    if extra:
        header.add_extra_dims([laspy.ExtraBytesParams(name=k, type=v.dtype) for k, v in
                               extra.items()])
    header.vlrs.append(laspy.VLR(user_id="lidar-outliers", record_id=7, description="test vlr",
                                 record_data=b"keep me"))
    if crs:
        if header.version.minor >= 4:
            header.vlrs.append(WktCoordinateSystemVlr(WKT))
        else:
            header.vlrs.append(laspy.VLR(user_id="LASF_Projection", record_id=2112,
                                         record_data=WKT.encode() + b"\0"))
    if evlr:
        header.evlrs = laspy.vlrs.vlrlist.VLRList(
            [laspy.VLR(user_id="lidar-outliers", record_id=42, record_data=b"evlr payload")]
        )
    las = laspy.LasData(header)
    n = xyz.shape[0]
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    rng = np.random.default_rng(seed)
    if random_dims:
        _fill_random(las, rng)
    if gps_time is not None:
        las.gps_time = gps_time
    if classification is not None:
        las.classification = classification
    if point_source_id is not None:
        las.point_source_id = point_source_id
    for name, values in (extra or {}).items():
        las[name] = values
    las.write(str(path))
    assert laspy.read(str(path)).header.point_count == n
    return path


def _fill_random(las: laspy.LasData, rng: np.random.Generator) -> None:
    """Random values in every standard dimension other than X, Y, Z (within their bit widths)."""
    n = len(las.points)
    for dim in las.point_format.dimensions:
        if dim.name in ("X", "Y", "Z") or not dim.is_standard:
            continue
        current = np.asarray(las[dim.name])
        if dim.name == "gps_time":
            las[dim.name] = rng.uniform(0, 1e6, n)
        elif current.dtype.kind == "f":
            las[dim.name] = rng.normal(size=current.shape).astype(current.dtype)
        else:
            bits = min(dim.num_bits // max(dim.num_elements, 1), 16)
            high = 2 ** bits
            if dim.name == "return_number" or dim.name == "number_of_returns":
                high = 8 if las.point_format.id < 6 else 16
            if dim.name == "classification" and las.point_format.id < 6:
                high = 32
            low = -(high // 2) if current.dtype.kind == "i" else 0
            hi = high // 2 if current.dtype.kind == "i" else high
            las[dim.name] = rng.integers(low, hi, size=current.shape).astype(current.dtype)


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20100101)
