"""One job over many workers: cut into tiles, the tiles run anywhere, the results merged.

The worker that gets a large job (more points than ``TILE_JOB_POINTS``, a pipeline that runs
in tiles, :mod:`lidar_outliers.tiling`) cuts its input into tile files and puts them, with a
manifest, into the job's storage (``jobs/<id>/tiles/``), then hands the tiles to the queue
(:func:`split_job`). Any worker runs a tile (:func:`run_job_tile`): it fetches the manifest and
the cells within the tile's halo, runs the pipeline and puts the tile's result back under a
name of its own, so a re-run overwrites it. A stage that estimates a parameter from the whole
cloud, or reads facts of the whole file (``transient``'s scan-line neighbours), first has a
round of tiles give their values and one task fix the estimate or combine the facts and put
each cell's part beside the cell (:func:`pin_job_stage`). Once every tile is done one worker
merges the results in the input's point order, writes the result and the statistics and ends
the job (:func:`merge_job`); a tile that fails ends the job as failed with its message
(:func:`fail_tiled_job`) and nothing of the result is left. The Celery side (a chord of tile
tasks and a merge task) is in ``worker/tasks.py``.

A pipeline that starts with stages along the scanners' time series (``temporal``) has them
streamed over the whole input by the worker that cuts the tiles, before any tile is queued
(:mod:`lidar_outliers.prepass`); their flags and scores go to the job's storage in the
input's point order, the tiles run the remaining stages on the points those left and the
merge starts from them.
"""

from __future__ import annotations

import json
import logging
import shutil
from collections import OrderedDict
from pathlib import Path
from typing import Any

import numpy as np

from lidar_outliers import lasio
from lidar_outliers.detectors import get_detector
from lidar_outliers.errors import CancelledError, LidarOutliersError
from lidar_outliers.jobs import layout
from lidar_outliers.jobs.callbacks import FAILED, SUCCESS
from lidar_outliers.jobs.execute import (
    Progress,
    Superseded,
    disk_full_message,
    fail_job,
    notify,
    quietly,
)
from lidar_outliers.jobs.settings import Settings, get_settings
from lidar_outliers.jobs.storage import ObjectMissing, Storage
from lidar_outliers.jobs.store import JobStatus, Store
from lidar_outliers.params import PipelineParams
from lidar_outliers.pipeline import check_noise_class, jsonable, resolve_stages
from lidar_outliers.prepass import Streamed, leading_streamed, run_streamed
from lidar_outliers.streaming import temporal_only
from lidar_outliers.tiling import (
    MANIFEST,
    HaloMemo,
    Settler,
    TileError,
    TileSet,
    auto_tile_size,
    cell_name,
    dropped_points,
    load_result,
    merge,
    next_whole_file_step,
    noise_truth,
    partition,
    pending_prepass,
    pin_stage,
    prepare_stage,
    result_name,
    run_tile,
    save_result,
    settles,
    stage_halos,
    tiled_statistics,
)

log = logging.getLogger(__name__)
Cell = tuple[int, int]
#: The halos this worker process's last tiles of a round needed, per (job, stage, round): the
#: next tile of the round it takes starts from them. A few rounds only: memory does not grow
#: with the jobs.
_HALO_MEMOS: OrderedDict[tuple[str, int | None, int], HaloMemo] = OrderedDict()
HALO_MEMOS_KEPT = 8
#: Name prefix of the streamed stages' arrays among the job's tile files.
STREAMED = "streamed_"


def split_job(
    settings: Settings, store: Store, storage: Storage, job_id: str, source: Path,
    scratch: Path, progress: Progress,
) -> list[Cell] | None:
    """Cut the job's input (a local copy at ``source``) into tiles in the job's storage and
    return the cells; None when the job runs on this worker (small, a stage that needs the
    whole cloud, or ``temporal`` alone, which streams over the file in bounded memory)."""
    job = store.get_job(job_id)
    assert job is not None
    params = PipelineParams.model_validate(job.inputs)
    facts = lasio.inspect_las(source)
    if (facts.points <= settings.tile_job_points or "trajectory" in job.facts
            or temporal_only(params)):
        return None
    if params.pipeline is not None and isinstance(
            stage_halos(params.pipeline[leading_streamed(params.pipeline):]), str):
        return None
    check_noise_class(params, facts.point_format)
    evidence = None
    if params.pipeline is None and params.profile == "auto":
        from lidar_outliers.profiles import file_evidence

        evidence = file_evidence(source, facts.to_dict())
    size = settings.tile_size or auto_tile_size(facts)
    tiles = partition(source, scratch / "cells", size, progress=progress,
                      progress_span=(0.0, 0.05))
    stages, note = resolve_stages(params, tiles.gps_probe(), facts.to_dict(), evidence)
    lead = leading_streamed(stages)
    if isinstance(stage_halos(stages[lead:]), str) or (lead and not tiles.has_gps_time):
        return None
    streamed = _stream_leading(storage, job_id, source, stages[:lead], tiles,
                               scratch / "streamed", progress) if lead else []
    for cell in tiles.cells:
        storage.put_file(layout.tile_key(job_id, cell_name(cell)), tiles.cell_path(cell),
                         move=True)
    dumped = [s.model_dump(mode="json") for s in stages]
    manifest = {**tiles.to_json(), "stages": dumped, "given": dumped, "estimated": {},
                "note": note, "facts": facts.to_dict(), "streamed": streamed}
    path = scratch / MANIFEST
    path.write_text(json.dumps(manifest))
    storage.put_file(layout.tile_key(job_id, MANIFEST), path, move=True)
    return sorted(tiles.cells)


def _stream_leading(storage: Storage, job_id: str, source: Path, stages: list, tiles: TileSet,
                    folder: Path, progress: Progress) -> list[dict[str, Any]]:
    """Stream the leading time-series stages over the input and put their arrays into the
    job's storage; their statistics (``info``, critical value) for the manifest."""
    first = run_streamed(source, stages, tiles.points, folder, progress=progress,
                         progress_at=0.05, scales=tiles.scales)
    np.save(folder / "dropped.npy", dropped_points(first.flags))
    names = [f"{STREAMED}{name}.npy" for name in ("flags", "dropped",
                                                   *(f"score_{s}" for s in first.scores))]
    entries = jsonable(first.stages)
    del first
    for name in names:
        storage.put_file(layout.tile_key(job_id, name), folder / name[len(STREAMED):],
                         move=True)
    shutil.rmtree(folder, ignore_errors=True)
    return entries


def _streamed_array(storage: Storage, job_id: str, name: str, folder: Path,
                    mode: str = "r") -> Any:
    """One array of the job's streamed stages, fetched into ``folder`` and mapped."""
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / name
    try:
        storage.get_file(layout.tile_key(job_id, STREAMED + name), path)
    except ObjectMissing:
        raise TileError(f"the streamed stages' {name} is missing") from None
    return np.load(path, mmap_mode=mode)  # type: ignore[call-overload]


def _streamed(storage: Storage, job_id: str, doc: dict[str, Any], stages: list,
              folder: Path, mode: str = "r") -> Streamed | None:
    """The file-order arrays of the stages the job ran over the whole input before its tiles,
    streamed or settled (None when there are none)."""
    if not doc.get("streamed"):
        return None
    lead = len(doc["streamed"])
    names = [s.detector for s in stages[:lead] if get_detector(s.detector).kind == "outlier"]
    return Streamed(_streamed_array(storage, job_id, "flags.npy", folder, mode),
                    {n: _streamed_array(storage, job_id, f"score_{n}.npy", folder)
                     for n in names}, list(doc["streamed"]))


def _put_settled(storage: Storage, job_id: str, settler: Settler, doc: dict[str, Any]) -> None:
    """Put the settled stages' arrays (the flags of every stage so far, which points they
    dropped, the new stages' scores) into the job's storage and their statistics into the
    manifest ``doc``; a round delivered again writes the same values."""
    kept = settler.finish()
    folder = settler.folder
    np.save(folder / "dropped.npy", dropped_points(kept.flags))
    flags = folder / "flags.npy"
    if not flags.exists():  # the streamed stages' flags, updated in place
        np.save(flags, kept.flags)
    names = ["flags.npy", "dropped.npy", *(f"score_{n}.npy" for n in settler.new_scores)]
    for name in names:
        storage.put_file(layout.tile_key(job_id, STREAMED + name), folder / name, move=True)
    doc["streamed"] = jsonable(kept.stages)


def _manifest(storage: Storage, job_id: str, folder: Path) -> tuple[TileSet, dict[str, Any]]:
    """The job's tile set (cells fetched from the storage when a tile needs them)."""
    try:
        doc = json.loads(storage.read_bytes(layout.tile_key(job_id, MANIFEST)))
    except ObjectMissing:
        raise TileError("the job's tile manifest is missing") from None
    folder.mkdir(parents=True, exist_ok=True)
    tiles = TileSet.from_json(folder, doc)

    def fetch(cell: Cell, path: Path) -> None:
        try:  # the cell's points, or a detector's facts for them (named by cell too)
            storage.get_file(layout.tile_key(job_id, path.name), path)
        except ObjectMissing:
            raise TileError(f"tile file {path.name} is missing") from None

    tiles.fetch = fetch
    return tiles, doc


def _stages(params: PipelineParams, doc: dict[str, Any]) -> tuple[PipelineParams, list]:
    """The stages the splitting worker resolved (the profile is chosen once per job)."""
    resolved = params.model_copy(update={"pipeline": None})
    stages = PipelineParams.model_validate({"pipeline": doc["stages"]}).pipeline
    assert stages is not None
    return resolved, list(stages)


def values_name(stage: int, cell: Cell, round_: int = 0) -> str:
    return f"values_{round_}_{stage}_{cell[0]}_{cell[1]}.npz"


def rounds_done(doc: dict[str, Any]) -> int:
    """How many rounds over the whole file (estimates, pre-passes) the manifest records: a
    stage may take several, so the round, not the stage, names a round's tasks and files."""
    return int(doc.get("rounds", 0))


def pending_phase(storage: Storage, job_id: str) -> tuple[int | None, bool, int]:
    """The stage whose estimate or facts from the whole file the job's tiles must gather
    first (None: the tiles run), whether such a round came before, and the round's number."""
    doc = json.loads(storage.read_bytes(layout.tile_key(job_id, MANIFEST)))
    tiles = TileSet.from_json(Path("."), doc)
    return (next_whole_file_step(_stages(PipelineParams(), doc)[1], tiles.prepared),
            bool(doc.get("estimated")), rounds_done(doc))


def job_cells(storage: Storage, job_id: str) -> list[Cell]:
    doc = json.loads(storage.read_bytes(layout.tile_key(job_id, MANIFEST)))
    return [(int(c), int(r)) for c, r, _ in doc["cells"]]


def pin_job_stage(settings: Settings, store: Store, storage: Storage, job_id: str,
                  stage: int, round_: int | None = None) -> bool:
    """Fix stage ``stage``'s estimate from every tile's values, or combine its facts from the
    whole file and put each cell's part into the storage, and record it in the manifest;
    False when the job is no longer running or round ``round_`` is done already (a message
    delivered again; None: the round pending now)."""
    job = store.get_job(job_id)
    if job is None or job.status is not JobStatus.running:
        return False
    scratch = layout.scratch(settings, f"pin-{job_id}")
    try:
        tiles, doc = _manifest(storage, job_id, scratch / "cells")
        params, stages = _stages(PipelineParams.model_validate(job.inputs), doc)
        current = rounds_done(doc)
        if next_whole_file_step(stages, tiles.prepared) != stage or (
                round_ is not None and round_ != current):
            return False
        lead = len(doc.get("streamed") or [])
        settler = None
        if settles(stages[lead:], stage - lead):
            kept = _streamed(storage, job_id, doc, stages, scratch / "streamed", mode="r+")
            settler = Settler(kept, stages[lead:stage], tiles.points, scratch / "settled")

        def values() -> Any:
            for cell in sorted(tiles.cells):
                path = scratch / values_name(stage, cell, current)
                try:
                    storage.get_file(layout.tile_key(job_id, path.name), path)
                except ObjectMissing:
                    raise TileError(f"tile {cell_name(cell)} has no values") from None
                yield load_result(path)
                path.unlink()

        results = values() if settler is None else settler.watch(values())
        if pending_prepass(stages, tiles.prepared) == stage:
            info = prepare_stage(
                tiles, stages[stage], results, scratch / "known",
                put=lambda path: storage.put_file(layout.tile_key(job_id, path.name), path,
                                                  move=True))
            doc["prepared"] = list(tiles.prepared)
        else:
            pinned, info = pin_stage(tiles, stages[stage], results, scratch / "values")
            doc["stages"][stage] = pinned.model_dump(mode="json")
        doc["estimated"][str(stage)] = {**doc["estimated"].get(str(stage), {}), **info}
        if settler is not None:
            _put_settled(storage, job_id, settler, doc)
        doc["rounds"] = current + 1
        path = scratch / MANIFEST
        path.write_text(json.dumps(doc))
        storage.put_file(layout.tile_key(job_id, MANIFEST), path, move=True)
        for cell in tiles.cells:
            quietly(storage.delete, layout.tile_key(job_id, values_name(stage, cell, current)))
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    return True


def run_job_tile(settings: Settings, store: Store, storage: Storage, job_id: str,
                 cell: Cell, values_of: int | None = None, round_: int | None = None) -> bool:
    """Run one tile of a running job and put its result (replacing an earlier run's); with
    ``values_of``, the values that stage estimates a parameter from, or gathers its facts from
    the whole file from, instead, for round ``round_`` (None: the round pending now).

    Returns False when the job is no longer running (dismissed, or failed by another tile) or
    the round is over (a message delivered again after its round was pinned).
    Raises what the tile raised; the caller fails the job with it.
    """
    job = store.get_job(job_id)
    if job is None or job.status is not JobStatus.running:
        return False
    scratch = layout.scratch(settings, f"tile-{job_id}")
    try:
        tiles, doc = _manifest(storage, job_id, scratch / "cells")
        params, stages = _stages(PipelineParams.model_validate(job.inputs), doc)
        if tuple(cell) not in tiles.cells:
            raise TileError(f"the job has no tile {cell_name(tuple(cell))}")
        current = rounds_done(doc)
        if values_of is not None and round_ is not None and round_ != current:
            return False
        # a tile needs only which points the streamed stages flagged, not their arrays
        lead = len(doc.get("streamed") or [])
        dropped = None if not lead else np.asarray(
            _streamed_array(storage, job_id, "dropped.npy", scratch / "streamed"))
        prepass = values_of is not None and pending_prepass(stages, tiles.prepared) == values_of
        own = None if values_of is None else values_of - lead  # among the tiled stages
        memo = _halo_memo((job_id, values_of, current))
        result = memo.seen(run_tile(tiles, tuple(cell), params, stages[lead:],
                                    values_of=None if prepass else own,
                                    prepass_of=own if prepass else None, dropped=dropped,
                                    settle=own is not None and settles(stages[lead:], own),
                                    start=memo.halos))
        path = scratch / (result_name(tuple(cell)) if values_of is None
                          else values_name(values_of, tuple(cell), current))
        save_result(path, result)
        storage.put_file(layout.tile_key(job_id, path.name), path, move=True)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    return True


def _halo_memo(key: tuple[str, int | None, int]) -> HaloMemo:
    """This process's :class:`HaloMemo` of a job's round (the latest few kept)."""
    memo = _HALO_MEMOS.pop(key, None) or HaloMemo()
    _HALO_MEMOS[key] = memo
    while len(_HALO_MEMOS) > HALO_MEMOS_KEPT:
        _HALO_MEMOS.popitem(last=False)
    return memo


def merge_job(settings: Settings, store: Store, storage: Storage, job_id: str) -> JobStatus | None:
    """Merge every tile's result in the input's order, store the result and the statistics,
    end the job; the tile files are removed whatever happens."""
    job = store.get_job(job_id)
    if job is None or job.status is not JobStatus.running:
        quietly(storage.delete_prefix, layout.tiles_prefix(job_id))
        return None
    scratch = layout.scratch(settings, f"merge-{job_id}")
    progress = Progress(store, job_id)
    try:
        stored = _merge(storage, job_id, job, scratch, progress)
    except Superseded:
        return None  # queued again: the job's files are the new delivery's
    except CancelledError:
        quietly(storage.delete_prefix, layout.job_prefix(job_id))
        return JobStatus.dismissed
    except LidarOutliersError as exc:
        return fail_tiled_job(store, storage, job_id, disk_full_message(exc) or str(exc),
                              settings)
    except Exception as exc:
        log.exception("merging the tiles of job %s failed", job_id)
        return fail_tiled_job(store, storage, job_id, disk_full_message(exc)
                              or f"internal error: {type(exc).__name__}: {exc}", settings)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    quietly(storage.delete_prefix, layout.tiles_prefix(job_id))
    done = store.transition(job_id, JobStatus.successful, "done",
                            stored_bytes=quietly(storage.prefix_bytes,
                                                 layout.job_prefix(job_id)) or stored)
    if done is None:
        quietly(storage.delete_prefix, layout.job_prefix(job_id))
        return JobStatus.dismissed
    notify(settings, done, SUCCESS)
    return JobStatus.successful


def _merge(storage: Storage, job_id: str, job: Any, scratch: Path, progress: Progress) -> int:
    from lidar_outliers.atomic import write_json_atomic
    from lidar_outliers.process import finish_statistics

    tiles, doc = _manifest(storage, job_id, scratch / "cells")
    params, stages = _stages(PipelineParams.model_validate(job.inputs), doc)
    progress(0.9, f"merging {len(tiles.cells)} tiles")

    def results() -> Any:
        for cell in sorted(tiles.cells):
            path = scratch / result_name(cell)
            try:
                storage.get_file(layout.tile_key(job_id, path.name), path)
            except ObjectMissing:
                raise TileError(f"tile {cell_name(cell)} has no result") from None
            yield load_result(path)
            path.unlink()

    first = _streamed(storage, job_id, doc, stages, scratch / "streamed")
    merged = merge(tiles, results(), stages, params, scratch / "merged", first)
    truth = noise_truth(tiles, params.reference_classes, scratch / "merged")
    suffix = ".laz" if job.laz else ".las"
    source, out = scratch / f"input{suffix}", scratch / f"result{suffix}"
    storage.get_file(layout.input_key(job_id, job.laz), source)
    lasio.write_result(source, out, flags=merged.flags, scores=merged.scores,
                       classification=merged.classification, laz=job.laz,
                       progress=progress, progress_span=(0.9, 0.99))
    facts = dict(doc["facts"], name=job.facts.get("name", doc["facts"].get("name")))
    given = list(PipelineParams.model_validate({"pipeline": doc["given"]}).pipeline or [])
    estimated = {int(k): v for k, v in doc.get("estimated", {}).items()}
    stats = tiled_statistics(merged, tiles, stages, params, facts, doc["note"], truth,
                             estimated, given, None if first is None else first.stages)
    stats["mode"] = "tiled over workers"
    if lead := leading_streamed(stages):
        stats["streamed"] = {"stages": [s.detector for s in stages[:lead]]}
    del merged, truth, first
    stats = finish_statistics(stats, out, job.laz, None, None)
    statistics = scratch / "statistics.json"
    write_json_atomic(statistics, stats)
    stored = storage.put_file(layout.result_key(job_id, job.laz), out, move=True)
    stored += storage.put_file(layout.statistics_key(job_id), statistics, move=True)
    return stored


def fail_tiled_job(store: Store, storage: Storage, job_id: str, message: str,
                   settings: Settings | None = None) -> JobStatus | None:
    """End a tiled job as failed with ``message`` (once: later calls change nothing); its
    tiles and any part of a result are removed, and its subscriber hears of the failure."""
    quietly(storage.delete_prefix, layout.tiles_prefix(job_id))
    if store.status(job_id) is not JobStatus.running:
        return None
    status = fail_job(store, storage, job_id, message)
    job = store.get_job(job_id)
    if status is JobStatus.failed and job is not None:
        notify(settings or get_settings(), job, FAILED)
    return status
