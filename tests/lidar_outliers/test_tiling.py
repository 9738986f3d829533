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
    HALO_GROWTH,
    HALO_STEP,
    NEED_MARGIN,
    POINT_DTYPE,
    HaloMemo,
    TileError,
    cell_name,
    load_region,
    outside_distance,
    partition,
    run_tile,
    wider_halos,
)
from tests.lasfiles import (
    STREET_TRANSIENT,
    airborne_scene,
    scanned_tile_scene,
    stop_scene,
    street_scene,
    tile_scene,
    write_las,
)

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


#: Pipelines that start with temporal: streamed along time over the whole file first, the
#: rest tile by tile on the points it left. A 1 ms max_gap leaves short scan-line segments
#: untested, so the later stage has outliers of its own to find.
STREAMED = {
    "temporal": [{"detector": "temporal"}],
    "temporal, then patch": [{"detector": "temporal"}, {"detector": "patch", "k": 30}],
    "temporal with short segments, then patch": [
        {"detector": "temporal", "max_gap": 0.001}, {"detector": "patch", "k": 30}],
    "temporal with short segments, then height_field": [
        {"detector": "temporal", "max_gap": 0.001, "sigma": [0.005, 0.08, 0.008]},
        {"detector": "height_field", "low": False}],
}


@pytest.fixture(scope="module", params=["in time order", "shuffled"])
def scanned(request, tmp_path_factory) -> Path:
    """The scene swept line by line by two scanners; its records in time order, or not."""
    shuffled = request.param == "shuffled"
    return scanned_tile_scene(tmp_path_factory.mktemp("scanned") / "scene.las",
                              shuffled=shuffled)


@pytest.mark.parametrize("name", list(STREAMED))
def test_streamed_stage_then_tiles_equals_whole_cloud(scanned, tmp_path, name):
    """temporal's time series lie across every tile: it is streamed over the file in time
    order (the records sorted on disk when they are not), the later stages run tile by tile
    on what it left, and flags, scores and every stage's counts are the whole run's, the
    streamed stage's info (sigma, max_gap per scanner, segments) too."""
    pipeline = STREAMED[name]
    whole, tiled = tmp_path / "whole.las", tmp_path / "tiled.las"
    stats_whole = process_file(scanned, whole, {"pipeline": pipeline, "classify": True})
    stats = process_file(scanned, tiled, {"pipeline": pipeline, "classify": True},
                         tile_size=TILE, chunk_points=1000)
    assert stats_whole["mode"] == "in memory" and stats["mode"] == "tiled"
    assert stats["streamed"]["stages"] == ["temporal"]
    a, b = _results(whole), _results(tiled)
    _assert_same(a, b, [s["detector"] for s in pipeline])
    for sw, st in zip(stats_whole["stages"], stats["stages"], strict=True):
        assert sw["points_flagged"] > 0 or sw["detector"] != "temporal"
        assert (sw["points_in"], sw["points_tested"], sw["points_flagged"]) == (
            st["points_in"], st["points_tested"], st["points_flagged"])
        assert st["critical_value"] == pytest.approx(sw["critical_value"])
    assert stats["stages"][0]["info"] == stats_whole["stages"][0]["info"]
    assert stats["overall"] == stats_whole["overall"]
    if len(pipeline) > 1 and "short" in name:
        assert stats["stages"][1]["points_flagged"] > 0
    assert not list(tmp_path.glob(".tiles-*"))


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


@pytest.fixture(scope="module")
def street(tmp_path_factory) -> Path:
    return street_scene(tmp_path_factory.mktemp("street") / "street.las")


STREET_TILE = 1.5  # metres: the box is 4 m long, the canopy 15 m, the one-pass stretch 12 m


@pytest.mark.parametrize("pipeline", [
    [STREET_TRANSIENT],
    [STREET_TRANSIENT, {"detector": "height_field", "sigma": 0.01, "low": False}],
    [{"detector": "height_field", "low": False}, STREET_TRANSIENT],
    [STREET_TRANSIENT, {"detector": "height_field"}],
], ids=["transient", "transient, then height_field", "height_field sigma auto, then transient",
        "transient, then height_field estimated"])
def test_transient_tiled_equals_whole_cloud(street, tmp_path, pipeline):
    """Persistence and the scan-line neighbours come from passes over the whole file, the
    clusters joined over the file: the whole cloud's result, tiles reading their scores."""
    whole, tiled = tmp_path / "whole.las", tmp_path / "tiled.las"
    stats_whole = process_file(street, whole, {"pipeline": pipeline})
    stats = process_file(street, tiled, {"pipeline": pipeline}, tile_size=STREET_TILE)
    assert stats_whole["mode"] == "in memory" and stats["mode"] == "tiled"
    assert stats["tiles"]["count"] >= 100
    a, b = _results(whole), _results(tiled)
    _assert_same(a, b, [s["detector"] for s in pipeline])
    for sw, st in zip(stats_whole["stages"], stats["stages"], strict=True):
        assert (sw["points_in"], sw["points_tested"], sw["points_flagged"]) == (
            st["points_in"], st["points_tested"], st["points_flagged"])
    assert stats["overall"] == stats_whole["overall"]
    flagged = (np.asarray(a.outlier_flags) & 128) != 0
    x, y, z = (np.asarray(a[d]) - o for d, o in (("x", 600_000), ("y", 5e6), ("z", 50)))
    box = (x >= 20) & (x <= 24) & (y >= 3.4) & (y <= 5.1) & (z >= 0.9) & (z <= 2.6)
    # the box flagged (by height_field first, at a few edge points), the canopy static
    assert (np.asarray(a.outlier_flags) != 0)[box].all() and not flagged[~box].any()
    transient = next(s for s in stats["stages"] if s["detector"] == "transient")
    assert transient["info"]["scan_lines"].startswith("in file order")


@pytest.mark.parametrize("where", ["scene", "street"])
def test_sigma_sampled_by_file_position_tiled_equals_whole_cloud(scene, street, tmp_path,
                                                                 monkeypatch, where):
    """``sigma: auto`` from every m-th point of the file (a sample of about 300 points here):
    the tiles fit the full patches of those alone and get the whole run's sigma, also when
    the stage before is settled in the same round."""
    import algorithms.height_field as hf

    monkeypatch.setattr(hf, "SIGMA_SAMPLE", 300)
    path, size = (scene, TILE) if where == "scene" else (street, STREET_TILE)
    pipeline = ([{"detector": "height_field", "low": False}] if where == "scene"
                else [STREET_TRANSIENT, {"detector": "height_field"}])
    whole, tiled = tmp_path / "whole.las", tmp_path / "tiled.las"
    stats_whole = process_file(path, whole, {"pipeline": pipeline})
    stats = process_file(path, tiled, {"pipeline": pipeline}, tile_size=size)
    _assert_same(_results(whole), _results(tiled), [s["detector"] for s in pipeline])
    sw, st = stats_whole["stages"][-1]["info"], stats["stages"][-1]["info"]
    assert st["sigma"] == pytest.approx(sw["sigma"], rel=1e-9)
    monkeypatch.setattr(hf, "SIGMA_SAMPLE", 10**9)  # every point: another sigma
    every = process_file(path, tmp_path / "every.las", {"pipeline": pipeline})
    assert every["stages"][-1]["info"]["sigma"] != sw["sigma"]


def test_transient_tiled_equals_whole_cloud_in_any_point_order(tmp_path):
    """Records not in time order: the scan-line neighbours come from a sort over the file."""
    street = street_scene(tmp_path / "shuffled.las", shuffled=True)
    pipeline = {"pipeline": [STREET_TRANSIENT]}
    whole, tiled = tmp_path / "whole.las", tmp_path / "tiled.las"
    process_file(street, whole, pipeline)
    stats = process_file(street, tiled, pipeline, tile_size=STREET_TILE)
    assert stats["stages"][0]["info"]["scan_lines"].startswith("sorted")
    a, b = _results(whole), _results(tiled)
    assert ((np.asarray(a.outlier_flags) & 128) != 0).sum() > 300
    _assert_same(a, b, ["transient"])


@pytest.mark.parametrize("shuffled", [False, True], ids=["time order", "any order"])
def test_transient_at_a_stop_tiled_equals_whole_cloud(tmp_path, shuffled):
    """A scanner standing in exhaust: its stop is found and cut into pieces over the whole
    file, in one pass in time order or sorted, each piece's beams crossing every tile; tiles
    of 1 m read the flags."""
    path = stop_scene(tmp_path / "stop.las", shuffled=shuffled)
    droplets = np.load(path.with_suffix(".npy"))
    pipeline = {"pipeline": [{"detector": "transient"}]}
    whole, tiled = tmp_path / "whole.las", tmp_path / "tiled.las"
    stats_whole = process_file(path, whole, pipeline)
    stats = process_file(path, tiled, pipeline, tile_size=1.0)
    assert stats["mode"] == "tiled" and stats["tiles"]["count"] >= 20
    a, b = _results(whole), _results(tiled)
    _assert_same(a, b, ["transient"])
    flagged = (np.asarray(a.outlier_flags) & 128) != 0
    assert flagged[droplets].mean() >= 0.5
    assert np.count_nonzero(flagged) - np.count_nonzero(flagged[droplets]) <= 5
    stops = stats["stages"][0]["info"]["stops"]
    assert stops["stop_pieces_placed"] == 3
    assert stats_whole["stages"][0]["info"]["stops"]["stop_pieces_placed"] == 3
    assert stops["order"].startswith("sorted" if shuffled else "in file order")


def test_transient_tiled_flags_the_canopy_when_max_extent_allows_it(street, tmp_path):
    """With max_extent above the canopy's 15 m the canopy floats and is flagged, whole and in
    tiles of 5 m alike (the canopy's cluster spans several tiles, joined over the file)."""
    stage = {**STREET_TRANSIENT, "max_extent": 20.0}
    whole, tiled = tmp_path / "whole.las", tmp_path / "tiled.las"
    process_file(street, whole, {"pipeline": [stage]})
    process_file(street, tiled, {"pipeline": [stage]}, tile_size=5.0)
    a, b = _results(whole), _results(tiled)
    _assert_same(a, b, ["transient"])
    flagged = (np.asarray(a.outlier_flags) & 128) != 0
    assert flagged[np.asarray(a.z) - 50 > 4].mean() > 0.9


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
    assert {"patch", "section", "dror", "snow", "detached", "height_field", "transient"} <= tiled
    streamed = {name for name, d in DETECTORS.items() if d.streams}
    assert streamed == {"temporal"} and not streamed & tiled


def test_streamed_stage_after_a_tiled_one_runs_whole_and_says_why(scene, tmp_path):
    """Only leading stages stream: temporal after patch would see patch's leftovers, which
    only the whole cloud knows before the tiles ran."""
    pipeline = {"pipeline": [{"detector": "patch", "k": 30}, {"detector": "temporal"}]}
    stats = process_file(scene, tmp_path / "tiled.las", pipeline, tile_size=TILE)
    assert stats["mode"] == "in memory"
    assert stats["tiling"].startswith("whole cloud in memory: temporal")


@pytest.mark.parametrize("name", [n for n, d in DETECTORS.items()
                                  if d.halo(d.parameters()) is None and not d.streams])
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


def test_a_tile_started_from_wider_halos_gives_the_same_result(scene, tmp_path):
    """The halos a tile starts from change the work, never the result: started from what the
    tile before needed, as a round over the file does (:class:`HaloMemo`)."""
    params = PipelineParams.model_validate({"pipeline": [{"detector": "patch", "k": 200}]})
    tiles = partition(scene, tmp_path / "cells", TILE)
    cell = max(tiles.cells, key=tiles.cells.get)
    first = run_tile(tiles, cell, params, list(params.pipeline))
    memo = HaloMemo()
    memo.seen(first)
    assert memo.halos is not None and memo.halos[0] > 2.0
    again = run_tile(tiles, cell, params, list(params.pipeline), start=memo.halos)
    assert again["halo"] <= first["halo"]  # what it needed, with a margin: not grown twice
    np.testing.assert_array_equal(again["index"], first["index"])
    np.testing.assert_array_equal(again["flags"], first["flags"])
    np.testing.assert_array_equal(again["score_patch"], first["score_patch"])


def test_halo_memo_keeps_the_widest_need_and_never_more_than_a_tile_used():
    memo = HaloMemo()
    memo.seen({"halos": np.array([2.0, 8.0]), "halos_needed": np.array([-math.inf, 5.0])})
    assert memo.halos == [0.0, 5.5]
    # a reach bounded by its halo reports the halo: the memo does not grow from it
    memo.seen({"halos": np.array([2.0, 5.5]), "halos_needed": np.array([1.0, 5.5])})
    assert memo.halos == [1.1, 5.5]
    memo.seen({"halos": np.array([2.0, 4.0]), "halos_needed": np.array([math.inf, 3.0])})
    assert memo.halos == [1.1, 5.5]


def test_halos_grow_where_a_stage_needs_more():
    assert wider_halos([2.0, 3.0], [1.0, -math.inf]) is None
    assert wider_halos([2.0, 3.0], [1.0, math.nan]) is None  # as before: nothing measured
    assert wider_halos([2.0, 3.0], [2.1, 3.0]) == [2.0 * HALO_STEP, 3.0]
    assert wider_halos([2.0, 3.0], [9.0, 1.0]) == [9.0 * NEED_MARGIN, 3.0]
    assert wider_halos([2.0, 3.0], [1.0, math.inf]) == [2.0, 3.0 * HALO_GROWTH]


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


def test_outside_distance_is_signed_chebyshev_distance_to_the_cell() -> None:
    class Grid:
        anchor = np.array([100.0, 200.0])
        tile_size = 10.0

    rng = np.random.default_rng(3)
    xy = Grid.anchor + rng.uniform(-15.0, 35.0, (500, 2))
    lo = Grid.anchor + np.array([10.0, 10.0])  # cell (1, 1)
    hi = lo + 10.0
    inside = np.all((xy >= lo) & (xy <= hi), axis=1)
    to_edge = np.min(np.hstack([xy - lo, hi - xy]), axis=1)
    beyond = np.max(np.hstack([lo - xy, xy - hi]), axis=1)
    expected = np.where(inside, -to_edge, beyond)
    np.testing.assert_allclose(outside_distance(xy, Grid, (1, 1)), expected)
    assert inside.any() and (~inside).any()


def test_points_on_tile_edges_belong_to_their_cell_at_any_coordinates() -> None:
    """A point that cells_of puts in a cell is never outside it, also where anchor + cell x
    size rounds the other way (a millimetre grid 1,000 km from the origin)."""
    from lidar_outliers.tiling import cells_of

    class Grid:
        anchor = np.array([-14.991, -14.995])
        tile_size = 2.0

    xy = np.array([[-4.991, -10.792], [-0.991, 7.868], [3.009, -6.219]])  # on x edges
    for offset in (0.0, 1e6, 4e7):
        shifted = xy + offset
        grid = type("Shifted", (), {"anchor": Grid.anchor + offset, "tile_size": 2.0})
        cell = cells_of(shifted, grid.anchor, grid.tile_size)
        for point, c in zip(shifted, cell, strict=True):
            assert outside_distance(point[None], grid, tuple(c))[0] <= 0.0


@pytest.mark.parametrize("offset", [0.0, 1e6])
def test_tiled_transient_keeps_points_on_tile_edges_far_from_the_origin(tmp_path, offset):
    """Millimetre coordinates, some exactly on tile edges: every point has a tile result and
    the tiled run equals the whole one."""
    rng = np.random.default_rng(0)
    n = 3000
    xyz = np.c_[rng.uniform(0, 30, n), rng.uniform(0, 30, n), rng.normal(0, 0.01, n)]
    header = laspy.LasHeader(point_format=3, version="1.2")
    header.scales = np.array([0.001] * 3)
    header.offsets = np.array([offset, offset, 0.0])
    las = laspy.LasData(header)
    las.x, las.y, las.z = (xyz + [offset, offset, 100.0]).T
    las.gps_time = np.arange(n) * 1e-5 + 1000.0
    las.point_source_id = np.ones(n, np.uint16)
    src = tmp_path / "edges.las"
    las.write(src)
    pipeline = {"pipeline": [{"detector": "transient"}]}
    whole, tiled = tmp_path / "whole.las", tmp_path / "tiled.las"
    process_file(src, whole, pipeline)
    stats = process_file(src, tiled, pipeline, tile_size=2.0)
    assert stats["mode"] == "tiled"
    _assert_same(_results(whole), _results(tiled), ["transient"])


def test_height_field_seen_again_tiled_equals_whole(scene, tmp_path):
    """``static_dt`` reads the times of a point's k nearest, which a tile's halo holds, and
    ``static_above`` the lowest return of the cells around it, which the reach adds."""
    pipeline = {"pipeline": [{"detector": "height_field", "static_dt": 0.5, "low": False}]}
    whole, tiled = tmp_path / "whole.las", tmp_path / "tiled.las"
    stats_whole = process_file(scene, whole, pipeline)
    stats = process_file(scene, tiled, pipeline, tile_size=TILE)
    info = stats_whole["stages"][0]["info"]
    assert stats["mode"] == "tiled" and info["points_static"] > 0
    assert info["points_seen_again_near_ground"] > 0
    _assert_same(_results(whole), _results(tiled), ["height_field"])


def test_height_field_foliage_tiled_equals_whole(tmp_path):
    """``foliage_reach`` reads a point's k nearest and, like ``static_above``, the lowest
    return of the cells around it: a crown seen once over tiles of 1.5 m."""
    from tests.algorithms.test_height_field import _crown_seen_once

    xyz, label = _crown_seen_once()
    path = write_las(tmp_path / "crown.las", xyz + [600_000, 5_000_000, 50],
                     offsets=(600_000, 5_000_000, 0))
    pipeline = {"pipeline": [{"detector": "height_field", "low": False, "static_dt": 0.0}]}
    whole, tiled = tmp_path / "whole.las", tmp_path / "tiled.las"
    stats_whole = process_file(path, whole, pipeline)
    stats = process_file(path, tiled, pipeline, tile_size=1.5)
    assert stats["mode"] == "tiled" and stats["tiles"]["count"] >= 100
    assert stats_whole["stages"][0]["info"]["points_in_foliage"] > 1000
    a = _results(whole)
    _assert_same(a, _results(tiled), ["height_field"])
    assert not np.asarray(a.outlier_flags)[label == 1].any()


def test_sigma_and_the_low_tests_spacing_and_voxel_are_fixed_in_one_round(
        street, tmp_path, monkeypatch):
    """Sigma and the spacing come from the same sample by file position, the voxel size from
    every point's small-piece ladder cut from its finest size: one round over the tiles gives
    each sample point its residual and its XY distance and every point its ladder, and pins
    all three as the whole run measures them."""
    import algorithms.height_field as hf
    from algorithms.detached import relative, voxel_size
    from lidar_outliers.detectors.detached import grid_origin
    from lidar_outliers.detectors.height_field import sigma_points
    from lidar_outliers.lasio import read_cloud
    from lidar_outliers.tiling import pin_stage

    monkeypatch.setattr(hf, "SIGMA_SAMPLE", 300)
    params = PipelineParams.model_validate({"pipeline": [{"detector": "height_field"}]})
    stages = list(params.pipeline)
    tiles = partition(street, tmp_path / "cells", STREET_TILE)
    results = [run_tile(tiles, cell, params, stages, values_of=0)
               for cell in sorted(tiles.cells)]
    assert all(r["values"].shape == (len(r["index"]), 3) for r in results)
    pinned, info = pin_stage(tiles, stages[0], results, tmp_path / "values")
    fixed = pinned.parameters()
    assert info["sigma_source"] == "auto" and hf.pending_estimate(fixed) is None
    cloud = read_cloud(street)
    local = relative(cloud.xyz, grid_origin(cloud))
    assert fixed.spacing_xy == pytest.approx(hf.sample_spacing(local, sigma_points(cloud)),
                                             rel=1e-12)
    whole = voxel_size(local, hf.LOW_PIECE_POINTS, float(fixed.spacing_xy), "auto")
    assert fixed.voxel == (0.0 if whole is None else whole)
