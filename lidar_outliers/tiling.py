"""A pipeline over a cloud of any size, tile by tile, in memory set by the tile size.

1. :func:`partition` streams the file once into one file per square XY cell of ``tile_size``
   metres (every point with its index in the file), on disk.
2. :func:`run_tile` loads one cell (the core) and the points of the neighbouring cells within
   the pipeline's halo, runs the stages and keeps the core's flags, scores and classes. The halo
   is the sum of the stages' declared halos (:class:`~lidar_outliers.detectors.base.Detector`):
   stage i's result is exact out to the halos of the stages after it, which is what those
   stages read. Where a detector's reach depends on the data (k nearest neighbours, radii that
   grow with range) the tile is run again with a wider halo until every point reached no
   further than it, so a tile gives the whole cloud's result for its points.
3. :func:`merge` writes the tiles' results into arrays on disk in the input's point order and
   the output file from them.

A pipeline that starts with stages along each scanner's time series (``temporal``: no halo)
runs them first over the whole file, streamed in time order (:mod:`lidar_outliers.prepass`),
then the rest tile by tile on the points they left; the merge starts from their arrays.

A stage that reads facts of the whole file (:class:`~lidar_outliers.detectors.base.Prepass`:
``transient``'s scan-line neighbours) gets them before its tiles run: each tile gives its points'
values (:func:`run_tile` with ``prepass_of``), :func:`prepare_stage` gathers them in file order
on disk, combines them over the whole file and writes each cell's part beside the cell's file,
where :func:`run_tile` reads them for its region (``Cloud.known``).

Such a round over the whole file runs the stages before it on every tile; their results for
the tile's core are final, so the round keeps them (:func:`settles`, :class:`Settler`): later
rounds and the tiles then run on the points those stages left, as after the streamed stages,
and every stage runs once over the file whatever the number of rounds.

The tiles are independent: :func:`process_tiled` runs them one after another here, the job
service spreads them over its workers (:mod:`lidar_outliers.jobs.tiles`).
"""

from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import laspy
import numpy as np

from algorithms.columns import column_max, column_min
from lidar_outliers import lasio
from lidar_outliers.atomic import write_json_atomic
from lidar_outliers.cloud import Cloud
from lidar_outliers.detectors import StageModel, get_detector
from lidar_outliers.errors import LidarOutliersError
from lidar_outliers.output import FLAGS_DTYPE
from lidar_outliers.pages import Releaser, filled, release, releasing
from lidar_outliers.params import FLAG_BITS, PipelineParams
from lidar_outliers.pipeline import (
    GROUND_CLASS,
    Progress,
    jsonable,
    noise_reference,
    overall_statistics,
    pipeline_statistics,
    run_pipeline,
    stage_entry,
)
from lidar_outliers.prepass import Streamed, leading_streamed, run_streamed

#: One point in a tile file.
POINT_DTYPE = np.dtype([
    ("xyz", "<f8", (3,)), ("gps_time", "<f8"), ("point_source_id", "<u2"),
    ("classification", "u1"), ("intensity", "<u2"), ("index", "<i8"),
])
#: Points per core tile the automatic tile size aims at at the mean density (denser parts of a
#: file get more). A halo costs in proportion to the tile's edge: on a simulated 4 M-point drive
#: the default pipeline took 656 s in tiles of 250 k points and 404 s in tiles of 600 k (before
#: reaches were bounded by dense cells; 146 s now, at a peak of 1.1 GB).
TILE_POINTS = 600_000
#: Files up to this many points run whole in memory unless a tile size is given. Run whole, a
#: simulated 2 M-point drive peaked at 1.5 GB with the default mobile pipeline and 1.6 GB with
#: ``detached`` (2.8 GB at 4 M points); in tiles the 4 M points took 1.8x the whole run's time.
WHOLE_CLOUD_POINTS = 2_000_000
MANIFEST = "tiles.json"
#: A tile whose points reach further than its halo is run again with a halo this much wider
#: than their reach (a region a little wider than needed costs less than a third run) ...
NEED_MARGIN = 1.1
#: ... and at least this many times its halo, so that a reach that grows with the region (a
#: piece cut at the region's edge) is caught up with in a few runs.
HALO_STEP = 1.25
#: A tile whose points need more than the points at hand is run again with its halo times this.
HALO_GROWTH = 2.0


class TileError(LidarOutliersError):
    """A tile file or a tile's result is missing or unreadable."""


@dataclass
class TileSet:
    """The cells of a partitioned file: where their files are and what the tiles share."""

    folder: Path
    tile_size: float
    anchor: np.ndarray  # (2,) XY lower-left corner of the file, local frame
    origin: np.ndarray  # (3,) the local frame's origin in file coordinates
    points: int
    has_gps_time: bool
    cells: dict[tuple[int, int], int]  # (column, row) -> points
    gps_range: tuple[float, float] | None = None  # finite gps_time min, max (None: no finite)
    #: Detectors whose pre-pass facts lie beside the cells (:func:`prepare_stage`).
    prepared: tuple[str, ...] = ()
    #: The file's coordinate resolution (header scales), for :attr:`Cloud.scales`.
    scales: np.ndarray | None = None
    #: Brings a cell's file into ``folder`` when it is not there (a worker that got the
    #: manifest only fetches the cells its tile needs from the job's storage).
    fetch: Callable[[tuple[int, int], Path], None] | None = None

    def cell_path(self, cell: tuple[int, int]) -> Path:
        return self.folder / cell_name(cell)

    def to_json(self) -> dict[str, Any]:
        return {"tile_size": self.tile_size, "anchor": self.anchor.tolist(),
                "origin": self.origin.tolist(), "points": self.points,
                "has_gps_time": self.has_gps_time,
                "gps_range": list(self.gps_range) if self.gps_range else None,
                "prepared": list(self.prepared),
                "scales": None if self.scales is None else self.scales.tolist(),
                "cells": [[c, r, n] for (c, r), n in sorted(self.cells.items())]}

    @classmethod
    def from_json(cls, folder: Path, doc: dict[str, Any]) -> TileSet:
        return cls(Path(folder), float(doc["tile_size"]), np.asarray(doc["anchor"]),
                   np.asarray(doc["origin"]), int(doc["points"]), bool(doc["has_gps_time"]),
                   {(int(c), int(r)): int(n) for c, r, n in doc["cells"]},
                   tuple(doc["gps_range"]) if doc.get("gps_range") else None,
                   prepared=tuple(doc.get("prepared", ())),
                   scales=None if doc.get("scales") is None else np.asarray(doc["scales"]))

    def gps_probe(self) -> np.ndarray | None:
        """Times that :func:`~lidar_outliers.pipeline.usable_gps_time` judges as it would the
        file's (none, all NaN, all the same, or usable)."""
        if not self.has_gps_time:
            return None
        if self.gps_range is None:
            return np.full(max(self.points, 1), np.nan)
        return np.asarray(self.gps_range, dtype=np.float64)

    @classmethod
    def load(cls, folder: Path) -> TileSet:
        return cls.from_json(folder, json.loads((Path(folder) / MANIFEST).read_text()))


def cell_name(cell: tuple[int, int]) -> str:
    return f"cell_{cell[0]}_{cell[1]}.bin"


def known_name(detector: str, cell: tuple[int, int]) -> str:
    return f"known_{detector}_{cell[0]}_{cell[1]}.bin"


def known_dtype(detector: str) -> np.dtype:
    """One point's record in a cell's file of a detector's pre-pass facts: its index in the
    file, then the detector's :attr:`~lidar_outliers.detectors.base.Prepass.dtype`."""
    prepass = get_detector(detector).prepass
    assert prepass is not None
    return np.dtype([("index", "<i8"), *[(f, prepass.dtype[f]) for f in prepass.dtype.names or ()]])


def result_name(cell: tuple[int, int]) -> str:
    return f"result_{cell[0]}_{cell[1]}.npz"


def cells_of(xy: np.ndarray, anchor: np.ndarray, size: float) -> np.ndarray:
    """(n, 2) int64 column and row of each point's cell (the one formula used everywhere)."""
    return np.floor((xy - anchor) / size).astype(np.int64)


def auto_tile_size(facts: lasio.LasFacts) -> float:
    """A tile edge giving about :data:`TILE_POINTS` points a tile at the file's mean density
    over its bounding box (at least 5 m)."""
    bounds = facts.bounds
    if not bounds or facts.points == 0:
        return 100.0
    dx = float(bounds["max"][0] - bounds["min"][0])
    dy = float(bounds["max"][1] - bounds["min"][1])
    area = max(dx * dy, max(dx, dy, 1.0))  # a straight drive along one axis still has an area
    return max(5.0, math.sqrt(area * TILE_POINTS / facts.points))


def partition(
    in_path: Path, folder: Path, tile_size: float, *,
    chunk_points: int = lasio.DEFAULT_CHUNK_POINTS, progress: Progress | None = None,
    progress_span: tuple[float, float] = (0.0, 1.0),
) -> TileSet:
    """Stream ``in_path`` into one file per XY cell of ``tile_size`` metres under ``folder``.

    The cells start at the header's lower-left corner; each file holds its points as
    :data:`POINT_DTYPE` records in file order. Memory: one chunk.
    """
    if not tile_size > 0:
        raise ValueError(f"tile_size must be > 0, got {tile_size}")
    folder.mkdir(parents=True, exist_ok=True)
    with lasio._laspy_errors(in_path.name), laspy.open(in_path) as reader:
        header = reader.header
    grid, origin = lasio.grid_origin(header)
    scales = np.asarray(header.scales)
    n = int(header.point_count)
    has_gps = "gps_time" in set(header.point_format.dimension_names)
    anchor = lasio.local_anchor(header, grid)
    cells: dict[tuple[int, int], int] = {}
    t_lo, t_hi = math.inf, -math.inf
    start = 0
    lo, hi = progress_span
    for chunk in lasio.iter_chunks(in_path, chunk_points):
        stop = start + len(chunk)
        rec = np.empty(stop - start, dtype=POINT_DTYPE)
        lasio.local_xyz(chunk, grid, scales, out=rec["xyz"])
        rec["gps_time"] = chunk.array["gps_time"] if has_gps else np.nan
        rec["point_source_id"] = chunk.array["point_source_id"]
        rec["classification"] = np.asarray(chunk.classification)
        rec["intensity"] = chunk.array["intensity"]
        rec["index"] = np.arange(start, stop, dtype=np.int64)
        finite = rec["gps_time"][np.isfinite(rec["gps_time"])]
        if finite.size:
            t_lo, t_hi = min(t_lo, float(finite.min())), max(t_hi, float(finite.max()))
        _append_by_cell(rec, cells_of(rec["xyz"][:, :2], anchor, tile_size), folder, cells)
        start = stop
        if progress is not None:
            progress(lo + (hi - lo) * stop / max(n, 1), f"cutting tiles: {stop:,} of {n:,} points")
    gps_range = (t_lo, t_hi) if t_lo <= t_hi else None
    tiles = TileSet(folder, float(tile_size), anchor, origin, n, has_gps, cells, gps_range,
                    scales=scales)
    write_json_atomic(folder / MANIFEST, tiles.to_json())
    return tiles


def _append_by_cell(rec: np.ndarray, ij: np.ndarray, folder: Path,
                    cells: dict[tuple[int, int], int]) -> None:
    order = np.lexsort((ij[:, 1], ij[:, 0]))
    ij, rec = ij[order], rec[order]
    new = np.r_[True, np.any(ij[1:] != ij[:-1], axis=1)] if len(ij) else np.zeros(0, bool)
    starts = np.r_[np.flatnonzero(new), len(ij)]
    for a, b in zip(starts[:-1], starts[1:], strict=True):
        cell = (int(ij[a, 0]), int(ij[a, 1]))
        with open(folder / cell_name(cell), "ab") as fh:
            rec[a:b].tofile(fh)
        cells[cell] = cells.get(cell, 0) + int(b - a)


# --------------------------------------------------------------------------- one tile


def stage_halos(stages: Iterable[StageModel], trajectory: bool = False) -> list[float] | str:
    """Each stage's declared halo, or the reason the pipeline cannot run in tiles."""
    halos = []
    prepassed: set[str] = set()
    for stage in stages:
        spec = get_detector(stage.detector)
        if trajectory and spec.uses_trajectory:
            return (f"{stage.detector} with a trajectory follows beams across the whole cloud "
                    "(free-space evidence)")
        if spec.prepass is not None:
            if stage.detector in prepassed:  # its facts from the whole file are kept by name
                return f"{stage.detector} comes twice, and each needs a pass over the whole file"
            prepassed.add(stage.detector)
        halo = spec.halo(stage.parameters())
        if halo is None:
            return (f"{stage.detector}: {spec.whole_cloud}" if spec.whole_cloud else
                    f"{stage.detector} with these parameters depends on the whole cloud")
        halos.append(float(halo))
    return halos


def read_cell(tiles: TileSet, cell: tuple[int, int]) -> np.ndarray:
    """The records of one cell (none for a cell without points); TileError when unreadable."""
    if cell not in tiles.cells:
        return np.zeros(0, dtype=POINT_DTYPE)
    return _read_records(tiles, cell, tiles.cell_path(cell), POINT_DTYPE)


def _read_records(tiles: TileSet, cell: tuple[int, int], path: Path, dtype: np.dtype
                  ) -> np.ndarray:
    """A file of one record per point of ``cell`` (fetched first when it is not here);
    TileError when it is unreadable or holds another number of records."""
    if tiles.fetch is not None and not path.exists():
        tiles.fetch(cell, path)
    try:
        size = path.stat().st_size
        if size != tiles.cells[cell] * dtype.itemsize:
            raise TileError(f"tile file {path.name} holds {size} bytes, expected "
                            f"{tiles.cells[cell]} points")
        return np.fromfile(path, dtype=dtype)
    except OSError as exc:
        raise TileError(f"tile file {path.name} cannot be read: {exc.strerror}") from None


def load_region(tiles: TileSet, cell: tuple[int, int], halo: float) -> tuple[np.ndarray, bool]:
    """The records within ``halo`` metres (XY) of ``cell``, and whether that is every cell."""
    ring = math.ceil(halo / tiles.tile_size) if math.isfinite(halo) else None
    if ring is None:
        wanted = list(tiles.cells)
    else:
        wanted = [c for c in tiles.cells
                  if abs(c[0] - cell[0]) <= ring and abs(c[1] - cell[1]) <= ring]
    parts = [read_cell(tiles, c) for c in sorted(wanted)]
    rec = np.concatenate(parts) if parts else np.zeros(0, dtype=POINT_DTYPE)
    keep = (np.flatnonzero(outside_distance(rec["xyz"][:, :2], tiles, cell) <= halo)
            if ring is not None else np.arange(len(rec)))
    rec = rec[keep[np.argsort(rec["index"][keep], kind="stable")]]  # file order, as whole
    return rec, len(rec) == tiles.points


def outside_distance(xy: np.ndarray, tiles: TileSet, cell: tuple[int, int]) -> np.ndarray:
    """(n,) Chebyshev XY distance from each point to the square of ``cell``, negative inside
    (minus the distance to its nearest edge).

    Measured in tile units from the same quotient as :func:`cells_of`, so a point that
    ``cells_of`` puts in the cell is never outside it: on an edge, ``anchor + cell x size``
    may round the other way (large coordinates), and a halo of 0 would lose the point."""
    size = tiles.tile_size
    # one axis at a time (columns of a record array are strided); per axis the position in
    # the cell, [0, 1) inside: > 0 outside, -(distance to an edge) inside
    u = (xy[:, 0] - tiles.anchor[0]) / size - cell[0]
    v = (xy[:, 1] - tiles.anchor[1]) / size - cell[1]
    return size * np.maximum(np.maximum(-u, u - 1.0), np.maximum(-v, v - 1.0))


def tile_cloud(tiles: TileSet, rec: np.ndarray, trajectory: np.ndarray | None = None) -> Cloud:
    return Cloud(
        xyz=np.ascontiguousarray(rec["xyz"]), origin=tiles.origin,
        gps_time=np.ascontiguousarray(rec["gps_time"]) if tiles.has_gps_time else None,
        point_source_id=np.ascontiguousarray(rec["point_source_id"]),
        classification=np.ascontiguousarray(rec["classification"]),
        intensity=np.ascontiguousarray(rec["intensity"]), trajectory=trajectory,
        anchor=tiles.anchor, position=np.ascontiguousarray(rec["index"]),
        file_points=tiles.points, scales=tiles.scales,
    )


def read_known(tiles: TileSet, detector: str, cell: tuple[int, int]) -> np.ndarray:
    """A cell's records of a detector's pre-pass facts (:func:`prepare_stage`)."""
    return _read_records(tiles, cell, tiles.folder / known_name(detector, cell),
                         known_dtype(detector))


def region_known(tiles: TileSet, rec: np.ndarray, detectors: Iterable[str]
                 ) -> dict[str, np.ndarray] | None:
    """The pre-pass facts of a region's points (``rec``), in its order, per detector of
    ``detectors`` (those that run here) gathered so far."""
    running = set(detectors)
    wanted = [d for d in tiles.prepared if d in running]
    if not wanted or len(rec) == 0:
        return None
    ij = cells_of(rec["xyz"][:, :2], tiles.anchor, tiles.tile_size)
    lo = column_min(ij)
    span = column_max(ij) - lo + 1
    keys = np.unique((ij[:, 0] - lo[0]) * span[1] + (ij[:, 1] - lo[1]))  # 1-D: fast to sort
    cells = [(int(lo[0] + key // span[1]), int(lo[1] + key % span[1])) for key in keys]
    known = {}
    for detector in wanted:
        parts = np.concatenate([read_known(tiles, detector, cell) for cell in cells])
        order = np.argsort(parts["index"], kind="stable")
        pos = order[np.minimum(np.searchsorted(parts["index"], rec["index"], sorter=order),
                               len(order) - 1)]
        if not np.array_equal(parts["index"][pos], rec["index"]):
            raise TileError(f"the {detector} pre-pass files do not hold every point of the tile")
        known[detector] = parts[pos]
    return known


def _check_prepared(tiles: TileSet, stages: list[StageModel]) -> None:
    """A stage with a pre-pass runs in a tile only with its facts from the whole file."""
    for stage in stages:
        if get_detector(stage.detector).prepass and stage.detector not in tiles.prepared:
            raise LidarOutliersError(f"{stage.detector} runs in tiles only after its pass over "
                                     "the whole file")


def run_tile(
    tiles: TileSet, cell: tuple[int, int], params: PipelineParams, stages: list[StageModel],
    trajectory: np.ndarray | None = None, values_of: int | None = None,
    prepass_of: int | None = None, dropped: np.ndarray | None = None, settle: bool = False,
    start: Sequence[float] | None = None,
) -> dict[str, Any]:
    """The pipeline's result for the points of ``cell``: the whole cloud's result for them.

    Returns ``index`` (the points' indices in the file), ``flags``, ``score_<name>`` per outlier
    stage, ``classification`` (with ``classify``), ``halo`` (metres used), ``halos`` and
    ``halos_needed`` (each stage's, used and what its reach needed, :func:`reach_needed`) and
    per stage its detector ``info`` and critical value (``stages``, JSON).
    ``trajectory``: (m, 4) in file coordinates.

    ``start``: halos to start from where wider than the declared ones (:class:`HaloMemo`); the
    result does not depend on them, only the work of growing the halos to the reach.

    ``values_of=i``: instead, the values stage i estimates a parameter from
    (:class:`~lidar_outliers.detectors.base.Estimate`) for the points of the cell: ``index``
    and ``values`` (NaN where none, and for points earlier stages flagged).

    ``prepass_of=i``: instead, stage i's pre-pass values
    (:class:`~lidar_outliers.detectors.base.Prepass`, with its halo) for the points of the cell:
    ``index``, ``in_stage`` (earlier stages left the point) and ``value_<name>`` (zero where
    not in the stage).

    ``settle`` (with ``values_of`` or ``prepass_of``): the result also holds the final
    ``flags``, scores and ``stages`` of the stages before that one (:func:`settles`), which
    the round has run anyway.

    ``dropped``: the sorted file indices of the points streamed or settled stages flagged
    before (:func:`dropped_points`): ``stages`` run on the other points, as the whole pipeline
    runs its later stages, and the result holds those only (with no stages: as they are).
    """
    if not stages and values_of is None:
        return _untouched(tiles, cell, params, dropped)
    local_traj = None if trajectory is None else trajectory - np.r_[0.0, tiles.origin]
    halos = stage_halos(stages, trajectory is not None)
    if isinstance(halos, str):
        raise LidarOutliersError(f"the pipeline cannot run in tiles: {halos}")
    if values_of is not None:
        stages, halos = stages[:values_of + 1], halos[:values_of + 1]
    if prepass_of is not None:
        prepass = get_detector(stages[prepass_of].detector).prepass
        assert prepass is not None
        stages = stages[:prepass_of + 1]
        halos = [*halos[:prepass_of], float(prepass.halo(stages[-1].parameters()))]
    if start is not None and len(start) == len(halos):
        halos = [max(h, float(s)) for h, s in zip(halos, start, strict=True)]
    run = stages if values_of is None and prepass_of is None else stages[:-1]
    _check_prepared(tiles, run)
    tile_params = params.model_copy(update={"pipeline": run or None, "reference_classes": None})
    # one stage: its reach reads no flags of its own, so the halo is settled before it runs once
    reach_first = values_of is None and prepass_of is None and len(run) == 1
    while True:
        total = float(sum(halos))
        rec, everything = load_region(tiles, cell, total)
        if dropped is not None:
            rec = rec[~_among(rec["index"], dropped)]
        cloud = tile_cloud(tiles, rec, local_traj)
        cloud.known = region_known(tiles, rec, (s.detector for s in run))
        result = run_pipeline(cloud, tile_params) if run and not reach_first else None
        flags = result.flags if result else np.zeros(len(cloud), FLAGS_DTYPE)
        outside = outside_distance(cloud.xyz[:, :2], tiles, cell)
        needed = [-math.inf] * len(halos) if everything else reach_needed(
            cloud, stages, halos, flags, outside)
        wider = wider_halos(halos, needed)
        if wider is None:
            break
        halos = wider
    core = np.all(cells_of(cloud.xyz[:, :2], tiles.anchor, tiles.tile_size) == cell, axis=1)
    if reach_first:  # only the core's results are read
        result = run_pipeline(replace(cloud, wanted=core), tile_params)
    if values_of is None and prepass_of is None:
        assert result is not None
        return _core_result(rec, core, result, halos, needed)
    out = _core_result(rec, core, result, halos, needed) if settle and result is not None else {
        "index": rec["index"][core], "halo": np.float64(sum(halos)),
        **_halo_entries(halos, needed)}
    # the values of the core's points read no further than the last stage's halo (its reach
    # was checked): the earlier stages' wider halos are not computed on again
    use = (flags == 0) & (outside <= halos[-1])
    if values_of is not None:
        out["values"] = _stage_values(cloud, stages[-1], use, core)[core]
        return out
    values = _prepass_values(cloud, stages[-1], use)
    out["in_stage"] = (flags == 0)[core]
    out.update({f"value_{name}": v[core] for name, v in values.items()})
    return out


def _halo_entries(halos: list[float], needed: list[float]) -> dict[str, np.ndarray]:
    return {"halos": np.asarray(halos, dtype=np.float64),
            "halos_needed": np.asarray(needed, dtype=np.float64)}


class HaloMemo:
    """Halos for the next tile of a round to start from (``run_tile``'s ``start``): the widest
    that the tiles before it needed, with a margin, each at most what its tile used (a reach
    bounded by the halo it fits in reports that halo, which must not ratchet up). Tiles of one
    survey reach about as far, so a tile is mostly loaded and checked once instead of grown
    from the declared halos again; a region a little wider than it needs costs less than a
    second region."""

    MARGIN = 1.1

    def __init__(self) -> None:
        self.halos: list[float] | None = None

    def seen(self, result: dict[str, Any]) -> dict[str, Any]:
        """Note what the result's reach needed; return the result."""
        if "halos_needed" in result:
            wanted = [min(self.MARGIN * float(n), float(h)) if math.isfinite(n) else 0.0
                      for n, h in zip(result["halos_needed"], result["halos"], strict=True)]
            self.halos = wanted if self.halos is None else [
                max(a, b) for a, b in zip(self.halos, wanted, strict=True)]
        return result


def _core_result(rec: np.ndarray, core: np.ndarray, result: Any, halos: list[float],
                 needed: list[float]) -> dict[str, Any]:
    """The pipeline's result for a tile's core points: flags, scores, classes, statistics."""
    out: dict[str, Any] = {"index": rec["index"][core], "flags": result.flags[core],
                           "halo": np.float64(sum(halos)), **_halo_entries(halos, needed)}
    for name, score in result.scores.items():
        out[f"score_{name}"] = score[core]
    if result.classification is not None:
        out["classification"] = result.classification[core]
    out["stages"] = json.dumps(jsonable([
        {"info": s.get("info"), "critical_value": s.get("critical_value")}
        for s in result.statistics["stages"]]))
    return out


def settles(stages: list[StageModel], step: int) -> bool:
    """Whether the round over the whole file for stage ``step`` settles the stages before it.

    That round runs them on every tile anyway, with their parameters fixed (``step`` is the
    first stage still waiting), and their results for a tile's core are final: kept in file
    order (:class:`Settler`), later rounds and the tiles run on the points they left instead
    of running them again. Stages that classify points are not settled (their classes of the
    points left are part of the result)."""
    return step > 0 and all(get_detector(s.detector).kind == "outlier" for s in stages[:step])


class Settler:
    """Keeps the results of the stages a round settles in file-order arrays on disk, after
    those of the stages already settled or streamed (``kept``; None: a new set of arrays
    under ``folder``); their statistics come from the largest tile, as a tile run's do."""

    def __init__(self, kept: Streamed | None, stages: list[StageModel], points: int,
                 folder: Path) -> None:
        folder.mkdir(parents=True, exist_ok=True)
        self.folder, self.stages = folder, stages
        if kept is None:
            # a new file of zeros ("w+" truncates)
            flags = np.lib.format.open_memmap(folder / "flags.npy", mode="w+",
                                              dtype=FLAGS_DTYPE, shape=(points,))
            kept = Streamed(flags, {})
        self.kept = kept
        self.new_scores: list[str] = []
        for stage in stages:
            name = stage.detector
            score = np.lib.format.open_memmap(folder / f"score_{name}.npy", mode="w+",
                                              dtype=np.float32, shape=(points,))
            filled(score, np.nan)
            kept.scores[name] = score
            self.new_scores.append(name)
        self._largest = (-1, "[]")
        self.pages = Releaser([kept.flags, *kept.scores.values()])

    def watch(self, results: Iterable[dict[str, Any]]) -> Iterable[dict[str, Any]]:
        """The tiles' results as they come, their settled part written on the way."""
        for res in releasing(results, self.pages):
            index = res["index"]
            self.kept.flags[index] = res["flags"]
            for name in self.new_scores:
                self.kept.scores[name][index] = res[f"score_{name}"]
            if index.size > self._largest[0]:
                self._largest = (int(index.size), str(res["stages"]))
            yield res

    def finish(self) -> Streamed:
        """The kept arrays with the settled stages' statistics appended."""
        entries = json.loads(self._largest[1])
        entries += [{}] * (len(self.stages) - len(entries))
        self.kept.stages = [*self.kept.stages, *entries[:len(self.stages)]]
        for arr in (self.kept.flags, *self.kept.scores.values()):
            if isinstance(arr, np.memmap):
                arr.flush()
        return self.kept


def dropped_points(flags: np.ndarray, step: int = 4_000_000) -> np.ndarray:
    """The sorted indices of the flagged points of ``flags`` (file order, e.g. a memory map),
    read in pieces: what a tile needs of the streamed stages, 8 bytes a flagged point."""
    parts = []
    for a in range(0, len(flags), step):
        parts.append(a + np.flatnonzero(np.asarray(flags[a:a + step])))
        release(flags)
    return np.concatenate(parts) if parts else np.zeros(0, dtype=np.int64)


def _among(index: np.ndarray, sorted_values: np.ndarray) -> np.ndarray:
    """(n,) bool: which of ``index`` are in the sorted array ``sorted_values``."""
    if sorted_values.size == 0:
        return np.zeros(index.shape, dtype=bool)
    pos = np.minimum(np.searchsorted(sorted_values, index), sorted_values.size - 1)
    return sorted_values[pos] == index


def _untouched(tiles: TileSet, cell: tuple[int, int], params: PipelineParams,
               dropped: np.ndarray | None) -> dict[str, Any]:
    """A tile's result when no stage is left to run: its points' flags 0 and input classes."""
    rec = read_cell(tiles, cell)
    if dropped is not None:
        rec = rec[~_among(rec["index"], dropped)]
    out: dict[str, Any] = {"index": rec["index"], "flags": np.zeros(len(rec), FLAGS_DTYPE),
                           "halo": np.float64(0.0), "stages": "[]"}
    if params.classify:
        out["classification"] = rec["classification"]
    return out


def _stage_values(cloud: Cloud, stage: StageModel, use: np.ndarray,
                  wanted: np.ndarray) -> np.ndarray:
    """(n,) or (n, m) the values a stage estimates from, computed on the points ``use`` (those
    earlier stages left, near enough; NaN else) for the points ``wanted``."""
    estimate = get_detector(stage.detector).estimate
    assert estimate is not None
    index = np.flatnonzero(use)
    sub = replace(cloud, wanted=wanted).subset(index)
    values = estimate.values(sub, stage.parameters())
    out = np.full((len(cloud), *values.shape[1:]), np.nan)
    out[index] = values
    return out


def _prepass_values(cloud: Cloud, stage: StageModel, use: np.ndarray) -> dict[str, np.ndarray]:
    """(n,) arrays of a stage's pre-pass values computed on the points ``use`` (0 else)."""
    prepass = get_detector(stage.detector).prepass
    assert prepass is not None
    index = np.flatnonzero(use)
    sub = cloud if index.size == len(cloud) else cloud.subset(index)
    out = {}
    for name, values in prepass.values(sub, stage.parameters()).items():
        full = np.zeros(len(cloud), dtype=values.dtype)
        full[index] = values
        out[name] = full
    return out


def pending_prepass(stages: list[StageModel], prepared: Iterable[str]) -> int | None:
    """The first stage whose facts from the whole file are not gathered yet, if any."""
    done = set(prepared)
    for i, stage in enumerate(stages):
        if get_detector(stage.detector).prepass is not None and stage.detector not in done:
            return i
    return None


def prepare_stage(
    tiles: TileSet, stage: StageModel, results: Iterable[dict[str, Any]], folder: Path,
    put: Callable[[Path], None] | None = None,
) -> dict[str, Any]:
    """Gather the tiles' pre-pass values of ``stage`` in file order on disk, combine them over
    the whole file (:class:`~lidar_outliers.detectors.base.Prepass`) and write each cell's part
    beside its file (``put``: hands each such file on, the job's storage); returns the
    statistics' info on it. Memory: what ``combine`` takes, the columns stay on disk."""
    spec = get_detector(stage.detector)
    assert spec.prepass is not None
    folder.mkdir(parents=True, exist_ok=True)
    n = tiles.points

    def mapped(name: str, dtype: Any) -> np.ndarray:
        # a new file of zeros ("w+" truncates): every field starts at 0
        arr = np.lib.format.open_memmap(folder / f"{stage.detector}_{name}.npy", mode="w+",
                                        dtype=dtype, shape=(n,))
        pages.add(arr)
        return arr

    pages = Releaser([])
    columns = {"in_stage": mapped("in_stage", np.bool_)}
    for res in releasing(results, pages):
        index = res["index"]
        columns["in_stage"][index] = res["in_stage"]
        for key in (k for k in res if k.startswith("value_")):
            if key[6:] not in columns:
                columns[key[6:]] = mapped(key[6:], res[key].dtype)
            columns[key[6:]][index] = res[key]
    columns["gps_time"] = mapped("gps_time", np.float64)
    columns["point_source_id"] = mapped("point_source_id", np.uint16)
    for axis in "xyz":
        columns[axis] = mapped(axis, np.float64)
    for cell in tiles.cells:
        rec = read_cell(tiles, cell)
        columns["gps_time"][rec["index"]] = rec["gps_time"]
        columns["point_source_id"][rec["index"]] = rec["point_source_id"]
        for k, axis in enumerate("xyz"):
            columns[axis][rec["index"]] = rec["xyz"][:, k]
        pages.moved(len(rec["index"]))
    out = mapped("known", spec.prepass.dtype)
    pages.now()
    info = spec.prepass.combine(stage.parameters(), columns, out)
    pages.now()
    with_index = known_dtype(stage.detector)
    for cell in sorted(tiles.cells):
        index = read_cell(tiles, cell)["index"]
        known = np.empty(len(index), dtype=with_index)
        known["index"] = index
        part = out[index]
        pages.moved(len(index))
        for f in spec.prepass.dtype.names or ():
            known[f] = part[f]
        path = tiles.folder / known_name(stage.detector, cell)
        fd, tmp = tempfile.mkstemp(dir=tiles.folder, prefix=".part-", suffix=".bin")
        with os.fdopen(fd, "wb") as fh:
            known.tofile(fh)
        os.replace(tmp, path)
        if put is not None:
            put(path)
    pages.now()
    del columns, out
    tiles.prepared = (*tiles.prepared, stage.detector)
    return info


def pending_estimate(stages: list[StageModel]) -> int | None:
    """The first stage that still estimates a parameter from the whole cloud, if any."""
    for i, stage in enumerate(stages):
        estimate = get_detector(stage.detector).estimate
        if estimate is not None and estimate.applies(stage.parameters()):
            return i
    return None


def pin_stage(
    tiles: TileSet, stage: StageModel, results: Iterable[dict[str, Any]], folder: Path,
) -> tuple[StageModel, dict[str, Any]]:
    """The stage with its estimate fixed from the tiles' values (gathered in file order on
    disk), and the statistics' note on it."""
    spec = get_detector(stage.detector)
    assert spec.estimate is not None
    folder.mkdir(parents=True, exist_ok=True)
    values: np.ndarray | None = None
    pages = Releaser([])
    for res in releasing(results, pages):
        if values is None:  # (n,) or (n, m): the first tile's values say which
            values = np.lib.format.open_memmap(
                folder / f"values_{stage.detector}.npy", mode="w+", dtype=np.float64,
                shape=(tiles.points, *res["values"].shape[1:]))
            filled(values, np.nan)
            pages.add(values)
        values[res["index"]] = res["values"]
    if values is None:  # no tile: no value
        values = np.full(tiles.points, np.nan)
    step = 4_000_000
    parts = [values[s:s + step] for s in range(0, tiles.points, step)]
    pinned, info = spec.estimate.pin(stage.parameters(), parts)
    release(values)
    del parts, values
    return spec.stage(**pinned.as_dict()), info


def reach_needed(
    cloud: Cloud, stages: list[StageModel], halos: list[float], flags: np.ndarray,
    outside: np.ndarray,
) -> list[float]:
    """Each stage's halo that its points that later stages rely on need in this region (-inf
    for a stage whose reach is not checked or with no such point; inf when a point needs more
    than the points at hand).

    Stage i must be exact within the halos of the stages after it (``outside``: each point's
    signed distance to the core, :func:`outside_distance`). The stages before it are exact
    within ``sum(halos[i:])``, so a point of it may reach that far past the core: its own
    distance inside the core and the halo ``halos[i]`` both count.
    """
    earlier = FLAGS_DTYPE(0)
    needed = [-math.inf] * len(stages)
    for i, stage in enumerate(stages):
        spec = get_detector(stage.detector)
        stage_in = (flags & earlier) == 0
        if spec.flag_bit is not None:
            earlier |= FLAGS_DTYPE(spec.flag_bit)
        if spec.reach is None:
            continue
        relied_on = outside <= sum(halos[i + 1:])
        index = np.flatnonzero(stage_in)
        if index.size == 0:
            continue
        allowed = sum(halos[i:]) - outside[index]
        used = spec.reach(cloud.subset(index), stage.parameters(), relied_on[index], allowed)
        short = (used - allowed)[relied_on[index]]
        if short.size:
            needed[i] = halos[i] + float(short.max())
    return needed


def wider_halos(halos: list[float], needed: list[float]) -> list[float] | None:
    """The halos to run a region again with when a stage needs more than its halo (each such
    one grows to its need with :data:`NEED_MARGIN`, at least :data:`HALO_STEP` times), None
    when every stage's fits."""
    if not any(n > h for n, h in zip(needed, halos, strict=True)):
        return None
    return [h if not n > h else
            max(h * HALO_STEP, n * NEED_MARGIN) if math.isfinite(n) else unbounded_growth(h)
            for h, n in zip(halos, needed, strict=True)]


def unbounded_growth(halo: float) -> float:
    """The next halo for a point that needs more than the points at hand (reach inf: fewer
    than k neighbours, too few surface points or floor cells around): the halo grows by
    :data:`HALO_GROWTH` until the region holds enough, or every point, rather than jumping to
    the whole cloud (a sparse tile over water of a large file would load all of it)."""
    return halo * HALO_GROWTH if halo > 0 else math.inf


def save_result(path: Path, result: dict[str, Any]) -> None:
    """Write a tile's result atomically (a re-run overwrites it whole)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".part-", suffix=".npz")
    with os.fdopen(fd, "wb") as fh:
        np.savez(fh, **result)
    os.replace(tmp, path)


def load_result(path: Path) -> dict[str, Any]:
    try:
        with np.load(path) as data:
            return {k: data[k] for k in data.files}
    except (OSError, ValueError) as exc:
        raise TileError(f"tile result {path.name} cannot be read: {exc}") from None


# --------------------------------------------------------------------------- merging


@dataclass
class Merged:
    """The pipeline's arrays for the whole file, on disk (memory maps) in file order."""

    flags: np.ndarray
    scores: dict[str, np.ndarray]
    classification: np.ndarray | None
    tile_stages: list[list[dict[str, Any]]]
    halos: list[float]
    sizes: list[int]


def merge(
    tiles: TileSet, results: Iterable[dict[str, Any]], stages: list[StageModel],
    params: PipelineParams, folder: Path, first: Streamed | None = None,
) -> Merged:
    """Scatter the tiles' results into memory-mapped arrays in the input's order.

    ``first``: the arrays of the streamed or settled stages that ran before the tiles (the
    tiles then hold the points those left; the points they flagged have their results)."""
    n = tiles.points
    folder.mkdir(parents=True, exist_ok=True)

    def mapped(name: str, dtype: Any, fill: float) -> np.ndarray:
        arr = np.lib.format.open_memmap(folder / f"{name}.npy", mode="w+", dtype=dtype,
                                        shape=(n,))
        filled(arr, fill)
        return arr

    flags = mapped("flags", FLAGS_DTYPE, 0)
    scores = {s.detector: mapped(f"score_{s.detector}", np.float32, np.nan) for s in stages
              if get_detector(s.detector).kind == "outlier"}
    classes = mapped("classification", np.uint8, 0) if params.classify else None
    seen = mapped("seen", np.bool_, False)
    pages = Releaser([flags, *scores.values(), classes, seen])
    if first is not None:
        _start_from(first, flags, scores, classes, seen, params.noise_class)
    tile_stages, halos, sizes = [], [], []
    for res in releasing(results, pages):
        index = res["index"]
        flags[index] = res["flags"]
        seen[index] = True
        for name, arr in scores.items():
            if first is None or name not in first.scores:
                arr[index] = res[f"score_{name}"]
        if classes is not None:
            classes[index] = res["classification"]
        tile_stages.append(json.loads(str(res["stages"])))
        halos.append(float(res["halo"]))
        sizes.append(int(index.size))
    missing = n - int(np.count_nonzero(seen))
    if missing:
        raise TileError(f"{missing} points have no tile result")
    return Merged(flags, scores, classes, tile_stages, halos, sizes)


def tiled_statistics(
    merged: Merged, tiles: TileSet, stages: list[StageModel], params: PipelineParams,
    facts: dict[str, Any], note: dict[str, Any], truth: np.ndarray | None,
    estimated: dict[int, dict[str, Any]] | None = None,
    given: list[StageModel] | None = None,
    streamed: list[dict[str, Any]] | None = None,
) -> dict[str, Any]:
    """The statistics of a tiled run: counts over all points, each stage's ``info`` and critical
    value from the largest tile. ``estimated``: per stage index, what was estimated from the
    whole cloud; ``given``: the stages as the job gave them (before estimates were fixed);
    ``streamed``: ``info`` and critical value of the leading stages streamed over the whole
    file (:mod:`lidar_outliers.prepass`), which the tiles did not run."""
    flags = merged.flags
    earlier = FLAGS_DTYPE(0)
    entries = []
    biggest = int(np.argmax(merged.sizes)) if merged.sizes else 0
    streamed = streamed or []
    for i, stage in enumerate(stages):
        spec = get_detector(stage.detector)
        stage_in = (flags & earlier) == 0
        entry = stage_entry(given[i] if given else stage, int(np.count_nonzero(stage_in)))
        if i < len(streamed):
            first = streamed[i]
        else:
            first = (merged.tile_stages[biggest][i - len(streamed)] if merged.tile_stages
                     else {})
        entry["info"] = first.get("info")
        if estimated and i in estimated and isinstance(entry["info"], dict):
            entry["info"] = {**entry["info"], **estimated[i]}
        if spec.kind == "outlier":
            bit = FLAGS_DTYPE(spec.flag_bit)
            flagged = (flags & bit) != 0
            entry.update(points_tested=int(np.count_nonzero(~np.isnan(merged.scores[spec.name]))),
                         points_flagged=int(np.count_nonzero(flagged)),
                         critical_value=first.get("critical_value"))
            earlier |= bit
            if truth is not None:
                from algorithms.metrics import outlier_confusion

                entry["confusion"] = outlier_confusion(truth[stage_in], flagged[stage_in])
        else:
            cls = merged.classification
            ground = (None if cls is None
                      else int(np.count_nonzero(cls[stage_in] == GROUND_CLASS)))
            entry.update(points_tested=int(np.count_nonzero(stage_in)), points_flagged=0,
                         points_ground=ground)
        entries.append(entry)
        release(flags, *merged.scores.values(), merged.classification, truth)
    confusion = None
    if truth is not None:
        from algorithms.metrics import outlier_confusion

        confusion = outlier_confusion(truth, flags != 0)
    by_bit = {name: int(np.count_nonzero(flags & FLAGS_DTYPE(bit))) for name, bit in
              FLAG_BITS.items()}
    overall = overall_statistics(int(flags.size), int(np.count_nonzero(flags)), by_bit, confusion)
    stats = pipeline_statistics(params, facts, note, entries, overall)
    stats["mode"] = "tiled"
    stats["tiles"] = {"tile_size": tiles.tile_size, "count": len(tiles.cells),
                      "largest_tile_points": max(tiles.cells.values(), default=0),
                      "halo_max": max(merged.halos, default=0.0)}
    return stats


def _start_from(first: Streamed, flags: np.ndarray, scores: dict[str, np.ndarray],
                classes: np.ndarray | None, seen: np.ndarray, noise_class: int) -> None:
    """The merged arrays as the streamed stages left them, chunk by chunk: their flags and
    scores; the points they flagged are done (noise, with ``classify``)."""
    step = 4_000_000
    for a in range(0, len(flags), step):
        part = np.asarray(first.flags[a:a + step])
        flags[a:a + step] = part
        seen[a:a + step] = part != 0
        if classes is not None:
            classes[a:a + step][part != 0] = noise_class
        for name, score in first.scores.items():
            scores[name][a:a + step] = score[a:a + step]
        release(first.flags, *first.scores.values(), flags, *scores.values(), classes, seen)


def noise_truth(tiles: TileSet, reference: list[int] | None, folder: Path) -> np.ndarray | None:
    """(n,) bool on disk: the points whose input class is a noise reference class."""
    noise = noise_reference(reference)
    if not noise:
        return None
    truth = np.lib.format.open_memmap(folder / "truth.npy", mode="w+", dtype=np.bool_,
                                      shape=(tiles.points,))
    pages = Releaser([truth])
    for cell in tiles.cells:
        rec = read_cell(tiles, cell)
        truth[rec["index"]] = np.isin(rec["classification"], noise)
        pages.moved(len(rec["index"]))
    pages.now()
    return truth


# --------------------------------------------------------------------------- one machine


def next_whole_file_step(stages: list[StageModel], prepared: Iterable[str]) -> int | None:
    """The first stage still waiting for an estimate or a pre-pass over the whole file (each
    runs the stages before it, so the earliest goes first)."""
    steps = [i for i in (pending_estimate(stages), pending_prepass(stages, prepared))
             if i is not None]
    return min(steps, default=None)


def process_tiled(
    in_path: Path, out_path: Path, params: PipelineParams, facts: lasio.LasFacts,
    evidence: dict[str, Any] | None, *, tile_size: float, compress: bool,
    progress: Progress | None = None, chunk_points: int = lasio.DEFAULT_CHUNK_POINTS,
    trajectory: np.ndarray | None = None,
) -> dict[str, Any] | str:
    """Partition, run every tile here, merge, write ``out_path``; return the statistics, or
    the reason the pipeline cannot run in tiles (nothing written then)."""
    from lidar_outliers.pipeline import resolve_stages

    t0 = time.perf_counter()
    work = Path(tempfile.mkdtemp(prefix=".tiles-", dir=out_path.resolve().parent))
    try:
        tiles = partition(in_path, work / "cells", tile_size, chunk_points=chunk_points,
                          progress=progress, progress_span=(0.0, 0.1))
        stages, note = resolve_stages(params, tiles.gps_probe(), facts.to_dict(), evidence)
        given = list(stages)
        lead = leading_streamed(stages)
        halos = stage_halos(stages[lead:], trajectory is not None)
        if isinstance(halos, str):
            return halos
        if lead and not tiles.has_gps_time:
            return f"{stages[0].detector} needs gps_time, which this file does not have"
        t_cut = time.perf_counter()
        first = run_streamed(in_path, stages[:lead], tiles.points, work / "streamed",
                             chunk_points=chunk_points, progress=progress,
                             scales=tiles.scales) if lead else None
        streamed_seconds = 0.0 if first is None else first.seconds
        dropped = None if first is None else dropped_points(first.flags)
        done, rest = stages[:lead], stages[lead:]  # run over the whole file / still to run
        estimated: dict[int, dict[str, Any]] = {}
        rounds: list[dict[str, Any]] = []
        while (i := next_whole_file_step(rest, tiles.prepared)) is not None:
            t_round = time.perf_counter()
            settle = settles(rest, i)
            prepass = pending_prepass(rest, tiles.prepared) == i
            memo = HaloMemo()
            values: Iterable[dict[str, Any]] = (
                memo.seen(run_tile(tiles, cell, params, rest, trajectory, dropped=dropped,
                                   settle=settle, start=memo.halos,
                                   **{"prepass_of" if prepass else "values_of": i}))
                for cell in sorted(tiles.cells))
            settler = (Settler(first, rest[:i], tiles.points, work / f"settled_{len(done)}")
                       if settle else None)
            if settler is not None:
                values = settler.watch(values)
            if prepass:
                info = prepare_stage(tiles, rest[i], values, work / "known")
            else:
                pinned, info = pin_stage(tiles, rest[i], values, work / "values")
                rest = [*rest[:i], pinned, *rest[i + 1:]]
            estimated[len(done) + i] = {**estimated.get(len(done) + i, {}), **info}
            rounds.append({"stage": rest[i].detector,
                           "round": "pre-pass" if prepass else "estimate",
                           "seconds": round(time.perf_counter() - t_round, 4)})
            if settler is not None:
                first = settler.finish()
                dropped = dropped_points(first.flags)
                done, rest = [*done, *rest[:i]], rest[i:]
        stages = [*done, *rest]
        t_tiles = time.perf_counter()
        results, memo = [], HaloMemo()
        for k, cell in enumerate(sorted(tiles.cells)):
            path = work / "results" / result_name(cell)
            save_result(path, memo.seen(run_tile(tiles, cell, params, rest, trajectory,
                                                 dropped=dropped, start=memo.halos)))
            results.append(path)
            if progress is not None:
                progress(0.1 + 0.75 * (k + 1) / len(tiles.cells),
                         f"tile {k + 1} of {len(tiles.cells)}")
        t_run = time.perf_counter()
        merged = merge(tiles, (load_result(p) for p in results), stages, params, work / "merged",
                       first)
        truth = noise_truth(tiles, params.reference_classes, work / "merged")
        lasio.write_result(in_path, out_path, flags=merged.flags, scores=merged.scores,
                           classification=merged.classification, laz=compress,
                           chunk_points=chunk_points, progress=progress,
                           progress_span=(0.85, 1.0))
        stats = tiled_statistics(merged, tiles, stages, params, facts.to_dict(), note, truth,
                                 estimated, given, None if first is None else first.stages)
        if lead:
            stats["streamed"] = {"stages": [s.detector for s in stages[:lead]],
                                 "seconds": round(streamed_seconds, 4)}
        del merged, truth, first, dropped
    finally:
        shutil.rmtree(work, ignore_errors=True)
    stats["seconds"] = {"cut": round(t_cut - t0, 4), "detect": round(t_run - t_cut, 4),
                        "write": round(time.perf_counter() - t_run, 4),
                        "total": round(time.perf_counter() - t0, 4),
                        "whole_file_rounds": rounds, "tiles": round(t_run - t_tiles, 4)}
    return stats
