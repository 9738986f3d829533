"""The bounded sample read for the profile choice, and the header facts it adds."""

from __future__ import annotations

from pathlib import Path

import laspy
import numpy as np
import pytest

from lidar_outliers.lasio import inspect_las, read_cloud, read_profile_sample
from tests.lidar_outliers.platforms import aircraft, write

DATA = Path(__file__).resolve().parents[1] / "data"


@pytest.fixture(scope="module")
def tile(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("tile")
    return write(folder / "air.laz", aircraft(width=40.0, density=60.0, seed=4))


def test_small_file_is_read_whole(tile):
    sample = read_profile_sample(tile)
    cloud = read_cloud(tile)
    assert len(sample) == len(cloud) == sample.points_in_file and sample.runs == 1
    np.testing.assert_array_equal(sample.xyz, cloud.xyz)
    np.testing.assert_array_equal(sample.origin, cloud.origin)
    np.testing.assert_array_equal(sample.gps_time, cloud.gps_time)
    las = laspy.read(tile)
    np.testing.assert_allclose(sample.scan_angle, np.asarray(las.scan_angle) * 0.006)
    np.testing.assert_array_equal(sample.return_number, np.asarray(las.return_number))
    np.testing.assert_array_equal(sample.source, np.asarray(las.point_source_id) * 16)


@pytest.mark.parametrize("max_points, run_points", [(20_000, 500), (3_000, 100)])
def test_large_file_gives_runs_of_consecutive_points_spread_over_it(tile, max_points,
                                                                     run_points):
    """Seeks (files over 4 x max_points) or one pass: either way runs of consecutive points,
    at most max_points of them, from the start to the end of the file."""
    sample = read_profile_sample(tile, max_points=max_points, run_points=run_points)
    t = read_cloud(tile).gps_time
    assert 0 < len(sample) <= max_points and sample.runs >= 2
    position = np.searchsorted(t, sample.gps_time)  # gps_time rises through the file
    assert position[0] == 0 and position[-1] > 0.9 * len(t)
    steps = np.diff(position)  # 0-2 within a run (two returns share a time), large between
    assert (steps >= 0).all() and np.count_nonzero(steps > 10) == sample.runs - 1


def test_header_texts_and_geographic_crs():
    facts = inspect_las(DATA / "formats" / "laspy__simple1_3.las")
    assert facts.system_identifier == "ALSXX" and facts.generating_software.startswith("ALSXX")
    assert not facts.geographic
    assert inspect_las(DATA / "formats" / "pdal__las__epsg_4326.las").geographic


def test_empty_file_gives_an_empty_sample():
    sample = read_profile_sample(DATA / "formats" / "pdal__las__no-points.las")
    assert len(sample) == 0 and sample.runs == 0 and sample.xyz.shape == (0, 3)
