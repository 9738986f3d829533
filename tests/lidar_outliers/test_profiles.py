"""Sensor profiles chosen from real LAS headers written and read by laspy."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from lidar_outliers.lasio import inspect_las
from lidar_outliers.params import default_stages
from lidar_outliers.profiles import choose_profile, default_pipeline, profile_stages
from tests.lasfiles import write_las

AIRBORNE = Path(__file__).resolve().parents[1] / "data" / "airborne" / "laspy__append-bug.laz"


def write_scan(path: Path, xyz: np.ndarray, ring: bool) -> Path:
    """Format 6, offsets at the floor of the minimum; a ``ring`` extra dimension if asked."""
    extra = {"ring": (np.arange(len(xyz)) % 64).astype(np.uint8)} if ring else None
    return write_las(path, xyz, point_format=6, offsets=np.floor(xyz.min(axis=0)), extra=extra,
                     vlrs=())


def test_spinning_sweep_in_sensor_frame(tmp_path):
    rng = np.random.default_rng(0)
    xyz = rng.uniform(-50, 50, (2000, 3))
    facts = inspect_las(write_scan(tmp_path / "sweep.las", xyz, ring=True)).to_dict()
    assert choose_profile(facts) == "spinning"
    profile, stages = default_pipeline(facts)
    assert profile == "spinning" and stages[0].detector == "snow"


def test_ring_without_the_sensor_origin_is_not_spinning(tmp_path):
    """A registered (map-frame) sweep: the origin test fails, snow's ranges would be wrong."""
    rng = np.random.default_rng(1)
    xyz = rng.uniform(0, 10, (20000, 3)) + np.array([5e5, 5e6, 100.0])
    facts = inspect_las(write_scan(tmp_path / "map.las", xyz, ring=True)).to_dict()
    assert choose_profile(facts) == "mobile"  # 200 points per m2: dense


def test_dense_strip_is_mobile_transient_then_height_field(tmp_path):
    rng = np.random.default_rng(2)
    xyz = rng.uniform(0, 5, (20000, 3)) + np.array([5e5, 5e6, 0.0])
    facts = inspect_las(write_scan(tmp_path / "strip.las", xyz, ring=False)).to_dict()
    assert choose_profile(facts) == "mobile"
    assert [s.detector for s in default_pipeline(facts)[1]] == \
        [s.detector for s in default_stages(facts["has_gps_time"])] == \
        ["transient", "height_field"]


def test_real_airborne_tile():
    facts = inspect_las(AIRBORNE).to_dict()
    assert choose_profile(facts) == "airborne"
    assert default_pipeline(facts)[1][0].detector == "detached"


def test_unknown_profile_is_refused():
    with pytest.raises(ValueError, match="unknown profile"):
        profile_stages("satellite", True)
