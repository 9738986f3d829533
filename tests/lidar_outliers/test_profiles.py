"""Sensor profiles chosen from real LAS headers written and read by laspy."""

from __future__ import annotations

from pathlib import Path

import laspy
import numpy as np
import pytest

from lidar_outliers.lasio import inspect_las
from lidar_outliers.params import default_stages
from lidar_outliers.profiles import choose_profile, default_pipeline, profile_stages

AIRBORNE = Path(__file__).resolve().parents[1] / "data" / "airborne" / "laspy__append-bug.laz"


def write_las(path: Path, xyz: np.ndarray, ring: bool, point_format: int = 6) -> Path:
    header = laspy.LasHeader(point_format=point_format, version="1.4")
    header.scales = np.array([0.001, 0.001, 0.001])
    header.offsets = np.floor(xyz.min(axis=0))
    if ring:
        header.add_extra_dim(laspy.ExtraBytesParams(name="ring", type=np.uint8))
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    if ring:
        las.ring = np.arange(len(xyz)) % 64
    las.write(path)
    return path


def test_spinning_sweep_in_sensor_frame(tmp_path):
    rng = np.random.default_rng(0)
    xyz = rng.uniform(-50, 50, (2000, 3))
    facts = inspect_las(write_las(tmp_path / "sweep.las", xyz, ring=True)).to_dict()
    assert choose_profile(facts) == "spinning"
    profile, stages = default_pipeline(facts)
    assert profile == "spinning" and stages[0].detector == "snow"


def test_ring_without_the_sensor_origin_is_not_spinning(tmp_path):
    """A registered (map-frame) sweep: the origin test fails, snow's ranges would be wrong."""
    rng = np.random.default_rng(1)
    xyz = rng.uniform(0, 10, (20000, 3)) + np.array([5e5, 5e6, 100.0])
    facts = inspect_las(write_las(tmp_path / "map.las", xyz, ring=True)).to_dict()
    assert choose_profile(facts) == "mobile"  # 200 points per m2: dense


def test_dense_strip_is_mobile_transient_then_height_field(tmp_path):
    rng = np.random.default_rng(2)
    xyz = rng.uniform(0, 5, (20000, 3)) + np.array([5e5, 5e6, 0.0])
    facts = inspect_las(write_las(tmp_path / "strip.las", xyz, ring=False)).to_dict()
    assert choose_profile(facts) == "mobile"
    assert [s.detector for s in default_pipeline(facts)[1]] == \
        [s.detector for s in default_stages(facts["has_gps_time"])] == \
        ["transient", "height_field"]


@pytest.mark.skipif(not AIRBORNE.exists(), reason="no copy of the airborne file")
def test_real_airborne_tile():
    facts = inspect_las(AIRBORNE).to_dict()
    assert choose_profile(facts) == "airborne"
    assert default_pipeline(facts)[1][0].detector == "detached"


def test_unknown_profile_is_refused():
    with pytest.raises(ValueError, match="unknown profile"):
        profile_stages("satellite", True)
