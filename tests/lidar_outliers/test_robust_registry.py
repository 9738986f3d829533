"""dror, snow and detached run through the registry and the pipeline on real LAS files."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import laspy
import numpy as np
import pytest

from algorithms.detached import detect_detached
from algorithms.dror import detect_dror
from algorithms.snow import detect_snow
from lidar_outliers.errors import MissingDimensionError, ParameterError
from lidar_outliers.lasio import read_cloud
from lidar_outliers.params import FLAG_BITS, parse_pipeline_params
from lidar_outliers.pipeline import run_pipeline
from tests.lasfiles import write_las

AIRBORNE = Path(__file__).resolve().parents[1] / "data" / "airborne" / "laspy__append-bug.laz"
SENSOR = np.array([512_345.0, 5_012_345.0, 101.5])  # sensor position in file coordinates


def sweep_file(path: Path, seed: int = 0) -> tuple[Path, np.ndarray, np.ndarray]:
    """A sparse ring sweep around SENSOR, with flakes, written with a large offset."""
    rng = np.random.default_rng(seed)
    az = np.deg2rad(np.arange(0.0, 360.0, 0.4))
    rings = [np.c_[r * np.cos(az), r * np.sin(az), np.full(az.size, -1.8)]
             for r in (4.0, 5.0, 6.5, 8.0, 10.0)]
    flakes = rng.uniform(-5, 5, (40, 3))
    local = np.vstack(rings + [flakes])
    intensity = np.r_[np.full(sum(len(r) for r in rings), 900), np.zeros(len(flakes), int)]
    write_las(path, local + SENSOR, gps_time=np.arange(len(local)) * 1e-5, point_format=6,
              offsets=np.floor(SENSOR), intensity=intensity, vlrs=())
    back = laspy.read(path)
    return path, np.c_[back.x, back.y, back.z] - SENSOR, np.asarray(back.intensity)


def run(cloud, stage: dict) -> np.ndarray:
    params = parse_pipeline_params({"pipeline": [stage], "classify": False})
    res = run_pipeline(cloud, params)
    return (res.flags & FLAG_BITS[stage["detector"]]) != 0


def test_dror_uses_the_sensor_origin_given_in_file_coordinates(tmp_path):
    path, rel, _ = sweep_file(tmp_path / "sweep.las")
    cloud = read_cloud(path)
    flags = run(cloud, {"detector": "dror", "origin": SENSOR.tolist(), "k_min": 3})
    expected = detect_dror(rel, k_min=3).flagged
    np.testing.assert_array_equal(flags, expected)
    assert expected.any() and not expected.all()


def test_snow_through_the_pipeline_matches_the_algorithm(tmp_path):
    path, rel, intensity = sweep_file(tmp_path / "sweep.las", seed=1)
    cloud = read_cloud(path)
    np.testing.assert_array_equal(cloud.intensity, intensity)
    expected = detect_snow(rel, intensity).flagged
    np.testing.assert_array_equal(run(cloud, {"detector": "snow", "origin": SENSOR.tolist()}),
                                  expected)
    assert expected.any() and not expected.all()


def test_snow_without_intensity_is_a_clear_message(tmp_path):
    cloud = replace(read_cloud(sweep_file(tmp_path / "sweep.las", seed=1)[0]), intensity=None)
    with pytest.raises(MissingDimensionError, match="intensity"):
        run(cloud, {"detector": "snow", "origin": SENSOR.tolist()})


def test_detached_through_the_pipeline_matches_the_algorithm():
    cloud = read_cloud(AIRBORNE)
    flags = run(cloud, {"detector": "detached"})
    corner = np.r_[cloud.anchor, 0.0]  # the pipeline's grids start at the file's corner
    np.testing.assert_array_equal(flags, detect_detached(cloud.xyz, origin=corner).flagged)
    assert 400 < flags.sum() < 700


def test_unknown_field_is_refused_with_its_name():
    with pytest.raises(ParameterError, match="k_surfce"):
        parse_pipeline_params({"pipeline": [{"detector": "detached", "k_surfce": 3}]})
