"""Tile by tile == the whole cloud: flags, scores and classes, for every detector, with tiles
much smaller than the features; the tile files, halos and merge on their own."""

from __future__ import annotations

import math
from pathlib import Path

import laspy
import numpy as np
import pytest

from lidar_outliers import process_file
from lidar_outliers.detectors import DETECTORS
from lidar_outliers.lasio import inspect_las
from lidar_outliers.params import PipelineParams
from lidar_outliers.tiling import (
    POINT_DTYPE,
    TileError,
    cell_name,
    load_region,
    partition,
    run_tile,
)
from tests.lasfiles import airborne_scene, tile_scene, write_las

SENSOR = (600_012.0, 5_000_012.0, 52.0)
TILE = 3.0  # metres: the box is 6 x 4 m, the sections 2 m, the patches about 1 m across

#: One pipeline per detector (and two stages together), parameters that make it flag something.
PIPELINES = {
    "patch": [{"detector": "patch", "k": 30}],
    "section": [{"detector": "section", "section_size": 2.0}],
    "dror": [{"detector": "dror", "origin": SENSOR, "multiplier": 8.0}],
    "snow": [{"detector": "snow", "origin": SENSOR, "multiplier": 20.0}],
    "height_field": [{"detector": "height_field", "sigma": 0.01, "low": False}],
    "height_field, sigma auto": [{"detector": "height_field", "low": False}],
    "height_field, then patch": [{"detector": "height_field", "sigma": 0.01, "low": False},
                                 {"detector": "patch", "k": 30}],
    "dror, then section": [
        {"detector": "dror", "origin": SENSOR, "multiplier": 8.0},
        {"detector": "section", "section_size": 2.0}],
    "height_field, low": [{"detector": "height_field", "low": True}],
    "detached": [{"detector": "detached"}],
    "detached, scaled, then patch": [
        {"detector": "detached", "piece_points": 200, "k_floor": 16, "k_surface": 32},
        {"detector": "patch", "k": 30}],
    "section, then detached, scaled": [  # estimated from the points section left
        {"detector": "section", "section_size": 2.0},
        {"detector": "detached", "piece_points": 200, "k_floor": 16, "k_surface": 32}],
}


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    return tile_scene(tmp_path_factory.mktemp("tiles") / "scene.las")


def _results(path: Path) -> laspy.LasData:
    return laspy.read(path)


def _assert_same(whole: laspy.LasData, tiled: laspy.LasData, detectors: list[str]) -> None:
    assert np.array_equal(whole.outlier_flags, tiled.outlier_flags)
    assert np.array_equal(whole.classification, tiled.classification)
    for name in detectors:
        if DETECTORS[name].kind != "outlier":
            continue
        a, b = np.asarray(whole[f"{name}_score"]), np.asarray(tiled[f"{name}_score"])
        assert np.array_equal(np.isnan(a), np.isnan(b)), name
        np.testing.assert_allclose(a[~np.isnan(a)], b[~np.isnan(b)], rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("name", list(PIPELINES))
def test_tiled_run_equals_whole_cloud(scene, tmp_path, name):
    pipeline = PIPELINES[name]
    whole, tiled = tmp_path / "whole.las", tmp_path / "tiled.las"
    stats_whole = process_file(scene, whole, {"pipeline": pipeline})
    stats = process_file(scene, tiled, {"pipeline": pipeline}, tile_size=TILE)
    assert stats_whole["mode"] == "in memory" and stats["mode"] == "tiled"
    assert stats["tiles"]["count"] >= 60  # 24 x 24 m in 3 m tiles
    a, b = _results(whole), _results(tiled)
    assert (a.outlier_flags != 0).any()
    _assert_same(a, b, [s["detector"] for s in pipeline])
    for sw, st in zip(stats_whole["stages"], stats["stages"], strict=True):
        assert (sw["points_in"], sw["points_tested"], sw["points_flagged"]) == (
            st["points_in"], st["points_tested"], st["points_flagged"])
    assert stats["overall"] == stats_whole["overall"]
    assert not list(tmp_path.glob(".tiles-*"))  # the tile files are gone
    for sw, st in zip(stats_whole["stages"], stats["stages"], strict=True):
        if "low_test" in sw["info"]:  # the pieces under the floor are found tile by tile too
            assert sw["info"]["low_test"]["points_flagged"] > 0
            assert st["info"]["low_test"]["voxel"] == sw["info"]["low_test"]["voxel"]
        if "sigma_source" in sw["info"]:  # estimated from the whole cloud either way
            assert st["info"]["sigma_source"] == sw["info"]["sigma_source"]
            assert st["info"]["sigma"] == pytest.approx(sw["info"]["sigma"], rel=1e-9)


@pytest.fixture(scope="module")
def airborne(tmp_path_factory) -> Path:
    return airborne_scene(tmp_path_factory.mktemp("airborne") / "airborne.las")


#: detached with pieces, floors and envelopes scaled to the small scenes, so that their 3 m
#: tiles run with halos of a few tiles (the defaults need regions of 1000 points and more).
DETACHED_SCALED = PIPELINES["detached, scaled, then patch"][0]


def test_detached_tiles_find_clusters_pieces_and_pits(airborne, tmp_path):
    """The birds (a small cluster over the envelope), the low clump (a piece under the lowest
    surface, 13 tiles across with its floor) and the pit: tiles 3 m wide give the whole
    cloud's flags, scores, spacings and voxel size, with finite halos."""
    pipeline = {"pipeline": [DETACHED_SCALED]}
    whole, tiled = tmp_path / "whole.las", tmp_path / "tiled.las"
    stats_whole = process_file(airborne, whole, pipeline)
    stats = process_file(airborne, tiled, pipeline, tile_size=TILE)
    assert stats["mode"] == "tiled" and stats["tiles"]["count"] >= 100
    assert math.isfinite(stats["tiles"]["halo_max"])
    info_whole, info = stats_whole["stages"][0]["info"], stats["stages"][0]["info"]
    for test in ("clusters", "pieces", "pits"):
        assert info_whole[test]["points_flagged"] > 0, test
    for key in ("median_spacing", "xy_spacing"):
        assert info[key] == info_whole[key], key
    assert info["pieces"]["voxel"] == info_whole["pieces"]["voxel"]
    _assert_same(_results(whole), _results(tiled), ["detached"])
    assert stats["overall"] == stats_whole["overall"]
    # with the estimates fixed, most tiles need a few tiles around them, not the cloud
    pinned = {**DETACHED_SCALED, "spacing": info_whole["median_spacing"],
              "spacing_xy": info_whole["xy_spacing"], "voxel": info_whole["pieces"]["voxel"]}
    params = PipelineParams.model_validate({"pipeline": [pinned]})
    tiles = partition(airborne, tmp_path / "cells", TILE)
    halos = [float(run_tile(tiles, c, params, list(params.pipeline))["halo"])
             for c in sorted(tiles.cells)]
    assert np.median(halos) <= 2 * TILE


@pytest.fixture(scope="module")
def moving(tmp_path_factory) -> Path:
    """Ground seen at many moments, a few blobs seen at one moment each over it (moving
    objects), and a 12 m band seen at one moment, four tiles long."""
    rng = np.random.default_rng(5)
    ground = np.column_stack([rng.uniform(0, 24, (3000, 2)), rng.normal(0, 0.01, 3000)])
    t_ground = rng.uniform(0, 100, 3000)
    blobs = [np.array([x, y, 1.0]) + rng.normal(0, 0.05, (40, 3))
             for x, y in rng.uniform(2, 22, (6, 2))]
    band = np.column_stack([np.linspace(4, 16, 400), 20 + rng.uniform(0, 0.3, 400),
                            1.5 + rng.normal(0, 0.01, 400)])
    xyz = np.vstack([ground, *blobs, band])
    t = np.r_[t_ground, np.repeat(rng.uniform(0, 100, 6), 40) + rng.uniform(0, 0.1, 240),
              50.0 + np.linspace(0, 0.2, 400)]
    order = np.argsort(t)
    return write_las(tmp_path_factory.mktemp("moving") / "moving.las",
                     xyz[order] + [600_000, 5_000_000, 50], gps_time=t[order] + 1000,
                     point_source_id=np.ones(len(t), np.uint16),
                     offsets=(600_000, 5_000_000, 0), vlrs=())


def test_transient_runs_whole_and_says_why(moving, tmp_path):
    """A floating cluster is judged by the returns its scanner fired just before and after it,
    which may lie anywhere in the cloud: transient does not run in tiles, and the pipeline's
    result is the whole cloud's."""
    whole, tiled = tmp_path / "whole.las", tmp_path / "tiled.las"
    pipeline = {"pipeline": [{"detector": "transient"},
                             {"detector": "height_field", "low": False}]}
    process_file(moving, whole, pipeline)
    stats = process_file(moving, tiled, pipeline, tile_size=4.0)
    assert stats["mode"] == "in memory" and "scan-line neighbours" in stats["tiling"]
    _assert_same(_results(whole), _results(tiled), ["transient", "height_field"])


def test_transient_with_a_trajectory_runs_whole_and_says_why(moving, tmp_path):
    traj = np.column_stack([np.linspace(999, 1200, 50), np.linspace(600_000, 600_024, 50),
                            np.full(50, 5_000_012.0), np.full(50, 52.0)])
    stats = process_file(moving, tmp_path / "out.las", {"pipeline": [{"detector": "transient"}]},
                         tile_size=TILE, trajectory=traj)
    assert stats["mode"] == "in memory" and "free-space" in stats["tiling"]


def test_every_detector_declares_whether_it_tiles():
    """A declared halo is a number of metres, or None (the stage runs on the whole cloud)."""
    for name, detector in DETECTORS.items():
        halo = detector.halo(detector.parameters())
        assert halo is None or halo >= 0, name
    tiled = {name for name, d in DETECTORS.items() if d.halo(d.parameters()) is not None}
    assert {"patch", "section", "dror", "snow", "detached", "height_field"} <= tiled
    assert "transient" not in tiled


@pytest.mark.parametrize("name", [n for n, d in DETECTORS.items()
                                  if d.halo(d.parameters()) is None])
def test_stage_without_halo_runs_whole_and_says_why(scene, tmp_path, name):
    whole, tiled = tmp_path / "whole.las", tmp_path / "tiled.las"
    pipeline = [{"detector": name}]
    process_file(scene, whole, {"pipeline": pipeline})
    stats = process_file(scene, tiled, {"pipeline": pipeline}, tile_size=TILE)
    assert stats["mode"] == "in memory"
    assert stats["tiling"].startswith(f"whole cloud in memory: {name}")
    _assert_same(_results(whole), _results(tiled), [name])


def test_narrow_halo_is_widened_until_every_patch_is_the_whole_clouds(scene, tmp_path):
    """Patches of k = 200 reach further than the declared first guess: the tile runs again."""
    params = PipelineParams.model_validate({"pipeline": [{"detector": "patch", "k": 200}]})
    tiles = partition(scene, tmp_path / "cells", TILE)
    cell = max(tiles.cells, key=tiles.cells.get)
    out = run_tile(tiles, cell, params, list(params.pipeline))
    assert out["halo"] > 2.0
    whole = tmp_path / "whole.las"
    process_file(scene, whole, params)
    score = np.asarray(_results(whole)["patch_score"])[out["index"]]
    np.testing.assert_allclose(out["score_patch"], score, rtol=1e-5, atol=1e-5)


def test_partition_keeps_every_point_once_in_its_cell(scene, tmp_path):
    tiles = partition(scene, tmp_path / "cells", TILE, chunk_points=1000)
    assert sum(tiles.cells.values()) == tiles.points == inspect_las(scene).points
    seen = np.concatenate([np.fromfile(tiles.cell_path(c), dtype=POINT_DTYPE)["index"]
                           for c in tiles.cells])
    assert np.array_equal(np.sort(seen), np.arange(tiles.points))
    rec, everything = load_region(tiles, next(iter(tiles.cells)), 100.0)
    assert everything and len(rec) == tiles.points


def test_corrupt_tile_file_is_an_error_naming_it(scene, tmp_path):
    tiles = partition(scene, tmp_path / "cells", TILE)
    cell = next(iter(tiles.cells))
    with open(tiles.folder / cell_name(cell), "ab") as fh:
        fh.write(b"x")
    params = PipelineParams.model_validate({"pipeline": [{"detector": "dror"}]})
    with pytest.raises(TileError, match=cell_name(cell)):
        run_tile(tiles, cell, params, list(params.pipeline))
