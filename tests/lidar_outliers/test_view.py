"""view: the decimated points a viewer draws, spread evenly in space with every outlier kept."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from lidar_outliers import view
from lidar_outliers.detectors import FLAG_BITS
from tests.lasfiles import write_las


def two_densities(rng: np.random.Generator, dense: int = 45_000, sparse: int = 5_000):
    """A flat square metre sampled densely beside one sampled sparsely."""
    xy = np.vstack([rng.uniform(0, 1, (dense, 2)), rng.uniform(0, 1, (sparse, 2)) + [1.0, 0.0]])
    return np.column_stack([xy, rng.normal(0, 0.001, len(xy))]).astype(np.float32)


def test_small_clouds_are_kept_whole(rng: np.random.Generator) -> None:
    xyz = rng.normal(size=(100, 3)).astype(np.float32)
    np.testing.assert_array_equal(view.decimate(xyz, np.zeros(100, np.uint16), 100),
                                  np.arange(100))


def test_every_outlier_is_kept_and_the_rest_spread_evenly(rng: np.random.Generator) -> None:
    xyz = two_densities(rng)
    flags = np.zeros(len(xyz), np.uint16)
    flagged = rng.choice(len(xyz), 300, replace=False)
    flags[flagged] = 1
    index = view.decimate(xyz, flags, 4_000)
    assert len(index) == 4_000 and np.all(np.diff(index) > 0)
    assert set(flagged) <= set(index)
    kept = index[flags[index] == 0]
    sparse_share = np.mean(xyz[kept, 0] >= 1.0)
    # a random sample would keep the scan's 10 %; even spreading gives each square about half
    assert 0.35 < sparse_share < 0.65, sparse_share


def test_too_many_outliers_are_sampled(rng: np.random.Generator) -> None:
    xyz = rng.normal(size=(1_000, 3)).astype(np.float32)
    flags = np.full(1_000, 2, np.uint16)
    flags[:10] = 0
    index = view.decimate(xyz, flags, 100)
    assert len(index) == 100 and np.all(flags[index] == 2)


def test_decimation_is_repeatable(rng: np.random.Generator) -> None:
    xyz = two_densities(rng, 5_000, 500)
    flags = np.zeros(len(xyz), np.uint16)
    np.testing.assert_array_equal(view.decimate(xyz, flags, 700), view.decimate(xyz, flags, 700))


def test_refuses_an_empty_budget() -> None:
    with pytest.raises(ValueError, match="max_points"):
        view.decimate(np.zeros((3, 3), np.float32), np.zeros(3, np.uint16), 0)


@pytest.fixture
def result_file(tmp_path: Path, rng: np.random.Generator) -> tuple[Path, np.ndarray, np.ndarray]:
    n = 20_000
    xyz = np.column_stack([rng.uniform(0, 50, n) + 500_000.0, rng.uniform(0, 50, n) + 5e6,
                           rng.uniform(0, 5, n) + 100.0])
    flags = np.zeros(n, np.uint16)
    flags[rng.choice(n, 150, replace=False)] = FLAG_BITS["patch"]
    flags[:5] |= FLAG_BITS["temporal"]
    path = write_las(tmp_path / "result.laz", xyz, offsets=(500_000.0, 5e6, 0.0),
                     extra={"outlier_flags": flags})
    return path, xyz, flags


def test_binary_layout_round_trip(result_file) -> None:
    path, xyz, flags = result_file
    header, points, got = view.parse(view.view_points(path, 50_000))
    assert header["points"] == header["total"] == len(xyz)
    assert header["outliers"] == header["outliers_kept"] == int(np.count_nonzero(flags))
    assert header["bits"] == FLAG_BITS
    assert points.dtype == np.float32 and got.dtype == np.uint16
    np.testing.assert_array_equal(got, flags)
    world = points.astype(np.float64) + header["centre"]
    np.testing.assert_allclose(world, xyz, atol=2e-3)  # float32 about the centre, mm grid
    assert np.abs(points).max() < 60  # about the centre, not the world origin


def test_decimation_keeps_every_outlier(result_file) -> None:
    path, xyz, flags = result_file
    header, points, got = view.parse(view.view_points(path, 2_000))
    assert header["points"] == 2_000 and header["total"] == len(xyz)
    assert int(np.count_nonzero(got)) == header["outliers"] == int(np.count_nonzero(flags))
    assert np.count_nonzero(got & FLAG_BITS["temporal"]) == 5
    assert view.view_points(path, 2_000) == view.view_points(path, 2_000)  # deterministic


def test_a_file_without_flags_has_none(tmp_path: Path, rng: np.random.Generator) -> None:
    path = write_las(tmp_path / "plain.las", rng.uniform(0, 10, (500, 3)))
    header, _, flags = view.parse(view.view_points(path))
    assert header["points"] == 500 and not flags.any()


def test_parse_refuses_other_bytes() -> None:
    with pytest.raises(ValueError, match="magic"):
        view.parse(b"LASF" + bytes(20))
