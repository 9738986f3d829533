"""Writing a simulated survey: the LAS delivery, its truth and its trajectory."""

from __future__ import annotations

from pathlib import Path

import laspy
import numpy as np

from lidar_outliers.atomic import atomic_path
from lidar_outliers.errors import ParameterError
from lidar_outliers.lasio import write_las_data
from lidar_outliers.tools.simulator.family import KIND_NAMES
from lidar_outliers.tools.simulator.generate import SimulatedCloud, facts_json

#: LAS 1.4 scan_angle unit for point formats 6-10.
SCAN_ANGLE_UNIT = 0.006


def stem(condition: str, seed: int) -> str:
    return f"{condition}_{seed}"


def write_simulation(cloud: SimulatedCloud, out_dir: Path) -> Path:
    """Write the LAS file, its truth and trajectory into ``out_dir``; returns the LAS path.

    ``<stem>.las``: what a real delivery holds (LAS 1.4 point format 6, 1 mm, classification
    0). ``<stem>.truth.npz``: ``is_outlier``, ``kind``, ``kind_names``, ``condition``,
    ``seed``, ``scale``; the system's true ``lever_arms`` (k, 4: point_source_id, forward,
    left, up), ``pose`` (m, 7: time, x, y, z, roll, pitch, heading), ``speed`` (m, 2: time,
    m/s) and ``facts`` (JSON: scanners, street, drive, outlier mix). ``<stem>.trajectory.txt``:
    time x y z of the reference point at 100 Hz. Each file is written to a temporary name and
    renamed, so a reader never sees half a file.
    """
    out_dir = Path(out_dir)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ParameterError(f"cannot create output directory {out_dir}: {exc.strerror}") from exc
    base = out_dir / stem(cloud.condition, cloud.seed)
    las_path = base.with_suffix(".las")
    write_las_data(to_las(cloud), las_path)
    with atomic_path(base.with_suffix(".truth.npz")) as tmp:
        _write_truth(cloud, tmp)
    with atomic_path(base.with_suffix(".trajectory.txt")) as tmp:
        np.savetxt(tmp, cloud.trajectory, fmt="%.4f", header="time x y z")
    return las_path


def _write_truth(cloud: SimulatedCloud, path: Path) -> None:
    pose = cloud.pose()
    with open(path, "wb") as fh:
        np.savez_compressed(
            fh,
            is_outlier=cloud.is_outlier,
            kind=cloud.kind,
            kind_names=np.array(KIND_NAMES),
            condition=np.array(cloud.condition),
            seed=np.array(cloud.seed),
            scale=np.array(cloud.scale),
            lever_arms=np.array(cloud.lever_arms(), dtype=float),
            pose=pose,
            speed=np.column_stack([cloud.motion.t, cloud.motion.speed]),
            facts=np.array(facts_json(cloud)),
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
