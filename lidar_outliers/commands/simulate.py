"""`lidar-outliers simulate`: write a simulated mobile-mapping cloud (condition A, B or C) as LAS.

Writes ``DIR/<condition>_<seed>.las`` (LAS 1.4, point format 6, 1 mm scale, classification 0),
the truth beside it (``.truth.npz``: ``is_outlier``, ``kind``, ``kind_names``) and the vehicle
trajectory (``.trajectory.txt``: time x y z of the roof reference point, 100 Hz). The physics is
in :mod:`lidar_outliers.simulator`; this module only does the files.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import laspy
import numpy as np

from lidar_outliers.simulator import KIND_NAMES, SimulatedCloud, simulate
from worker.errors import ParameterError

#: LAS 1.4 scan_angle unit for point formats 6-10.
SCAN_ANGLE_UNIT = 0.006


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "simulate",
        help="simulate a mobile-mapping cloud like the paper's A, B or C",
        description="Simulate a LYNX-like survey of a parking-lot strip with outliers in the "
        "share and character of the paper's Table 1, and write it as LAS with its truth.",
    )
    parser.add_argument("--condition", required=True, choices=("A", "B", "C"),
                        help="A: 1.0 %% clumped, B: 0.3 %% spread, C: 0.01 %% near the surface")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument("--out", required=True, type=Path, help="output directory")
    parser.add_argument("--scale", type=float, default=1.0,
                        help="shrink the strip and point count by this factor, 0.01-1 (default 1)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if not 0.01 <= args.scale <= 1.0:
        raise ParameterError(f"--scale must be between 0.01 and 1, got {args.scale}")
    start = time.perf_counter()
    cloud = simulate(args.condition, args.seed, args.scale)
    path = write_simulation(cloud, args.out)
    share = 100.0 * cloud.is_outlier.mean()
    print(f"{path}: {len(cloud):,} points, {int(cloud.is_outlier.sum()):,} outliers "
          f"({share:.2f} %), {time.perf_counter() - start:.1f} s")
    return 0


def stem(condition: str, seed: int) -> str:
    return f"{condition}_{seed}"


def write_simulation(cloud: SimulatedCloud, out_dir: Path) -> Path:
    """Write the LAS file, its truth and trajectory into ``out_dir``; returns the LAS path.

    Each file is written to a temporary name and renamed, so a reader never sees half a file.
    """
    out_dir = Path(out_dir)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ParameterError(f"cannot create output directory {out_dir}: {exc.strerror}") from exc
    base = out_dir / stem(cloud.condition, cloud.seed)
    las_path = base.with_suffix(".las")
    _atomic(las_path, lambda p: to_las(cloud).write(str(p)))
    _atomic(base.with_suffix(".truth.npz"), lambda p: _write_truth(cloud, p))
    _atomic(base.with_suffix(".trajectory.txt"),
            lambda p: np.savetxt(p, cloud.trajectory, fmt="%.4f", header="time x y z"))
    return las_path


def _atomic(path: Path, write) -> None:
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def _write_truth(cloud: SimulatedCloud, path: Path) -> None:
    with open(path, "wb") as fh:
        np.savez_compressed(
            fh,
            is_outlier=cloud.is_outlier,
            kind=cloud.kind,
            kind_names=np.array(KIND_NAMES),
            condition=np.array(cloud.condition),
            seed=np.array(cloud.seed),
            scale=np.array(cloud.scale),
        )


def to_las(cloud: SimulatedCloud) -> laspy.LasData:
    """The cloud as LAS 1.4 point format 6 at 1 mm scale, classification 0."""
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales = np.array([0.001, 0.001, 0.001])
    header.offsets = np.floor(cloud.xyz.min(axis=0)) if len(cloud) else np.zeros(3)
    header.system_identifier = "lidar-outliers simulator"
    header.generating_software = f"simulate {cloud.condition} seed {cloud.seed}"
    las = laspy.LasData(header)
    las.x = cloud.xyz[:, 0]
    las.y = cloud.xyz[:, 1]
    las.z = cloud.xyz[:, 2]
    las.gps_time = cloud.gps_time
    las.point_source_id = cloud.point_source_id
    las.intensity = cloud.intensity
    las.return_number = cloud.return_number
    las.number_of_returns = cloud.number_of_returns
    las.scan_angle = np.round(cloud.scan_angle / SCAN_ANGLE_UNIT).astype(np.int16)
    las.classification = np.zeros(len(cloud), dtype=np.uint8)
    return las
