"""Small synthetic mobile-scan clouds written with laspy, with known injected outliers."""

from __future__ import annotations

from pathlib import Path

import laspy
import numpy as np


def write_cloud(
    path: Path, n: int = 4000, *, seed: int = 0, laz: bool = False, point_format: int = 1,
    spikes: int = 20,
) -> np.ndarray:
    """Write a scan of a gently curved road profile along a straight track, ordered by
    gps_time (near 500,000 s, coordinates near a projected easting/northing), with ``spikes``
    points lifted by 2 m. Returns the indices of the spikes."""
    rng = np.random.default_rng(seed)
    t = 500_000.0 + np.arange(n) * 1e-4
    phase = np.arange(n) * 0.05
    x = 500_000.0 + 10.0 * (t - t[0]) + 3.0 * np.cos(phase)
    y = 5_000_000.0 + 3.0 * np.sin(phase)
    z = 100.0 + 0.02 * np.sin(phase) + rng.normal(0.0, 0.003, n)
    idx = np.sort(rng.choice(np.arange(20, n - 20), size=spikes, replace=False))
    z[idx] += 2.0
    header = laspy.LasHeader(point_format=point_format, version="1.2")
    header.scales = np.array([0.001, 0.001, 0.001])
    header.offsets = np.array([500_000.0, 5_000_000.0, 0.0])
    las = laspy.LasData(header)
    las.x, las.y, las.z = x, y, z
    if "gps_time" in las.point_format.dimension_names:
        las.gps_time = t
    las.point_source_id = np.ones(n, dtype=np.uint16)
    las.classification = np.ones(n, dtype=np.uint8)
    las.intensity = rng.integers(0, 1000, n).astype(np.uint16)
    las.write(str(path), do_compress=laz)
    return idx
