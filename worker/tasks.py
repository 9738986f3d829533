"""The Celery tasks: one delivery of a job (:func:`~lidar_outliers.jobs.execute.execute_job`),
and for a job cut into tiles the tile tasks, the merge and the error callback
(:mod:`lidar_outliers.jobs.tiles`).

The database schema is migrated once when the worker starts (before its pool forks); each pool
process then opens its own store and storage client on its first job.

A large job's tiles are a chord: a group of tile tasks, then the merge. Every task is
acknowledged late and re-queued when its worker dies, so a killed tile is run again and only it;
a tile's result has a name of its own, so a re-run overwrites it. A tile that fails ends the
job at once with its message (the other tiles then return without work), and the chord's error
callback (``link_error`` on the merge, which Celery also calls when a header task failed)
removes the tiles, so the chord never waits on a job that has ended.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import lru_cache
from typing import Any

from celery import chord, group
from celery.exceptions import SoftTimeLimitExceeded
from celery.signals import worker_init

from lidar_outliers.errors import LidarOutliersError
from lidar_outliers.jobs.execute import disk_full_message, execute_job
from lidar_outliers.jobs.queue import (
    MERGE_TILES_TASK,
    PIN_TILES_TASK,
    RUN_JOB_TASK,
    RUN_TILE_TASK,
    TILES_FAILED_TASK,
)
from lidar_outliers.jobs.settings import get_settings
from lidar_outliers.jobs.storage import Storage, open_storage
from lidar_outliers.jobs.store import TILED_HOST, Store
from lidar_outliers.jobs.tiles import (
    fail_tiled_job,
    job_cells,
    merge_job,
    pending_phase,
    pin_job_stage,
    run_job_tile,
)
from worker.celery_app import app

#: Redis set of a job's finished tiles (progress over all tiles, whichever worker ran them).
_DONE_KEY = "lidar_outliers:tiles-done:{}"


@worker_init.connect
def _migrate(**_: Any) -> None:
    """Bring the schema up to date at start-up; its connections are closed before the fork."""
    Store(get_settings().database_url).close()


@lru_cache
def _store() -> Store:
    return Store(get_settings().database_url, migrate=False)


@lru_cache
def _storage() -> Storage:
    return open_storage(get_settings())


def dispatch_tiles(job_id: str, cells: Sequence[tuple[int, int]]) -> None:
    """Queue one task per tile and after them all the merge; or, while a stage still
    estimates a parameter from the whole cloud, the tiles' values of it and after them the
    task that fixes it (and queues the next round)."""
    phase, estimated, round_ = pending_phase(_storage(), job_id)
    # progress: estimates take 5-45 %, the tiles the rest up to 90 % (the merge the last)
    span = (5, 45) if phase is not None else (45, 90) if estimated else (5, 90)
    header = group(run_tile.s(job_id, list(cell), len(cells), phase, span, round_)
                   for cell in cells)
    body = merge_tiles.si(job_id) if phase is None else pin_tiles.si(job_id, phase, round_)
    chord(header)(body.set(link_error=[tiles_failed.s(job_id)]))


@app.task(name=RUN_JOB_TASK, acks_late=True, reject_on_worker_lost=True)
def run_job(job_id: str, requeue: int = 0) -> str | None:
    """``requeue``: the job's re-queue count when the message was sent (0 from the API)."""
    status = execute_job(get_settings(), _store(), job_id,
                         time_limit_errors=(SoftTimeLimitExceeded,), storage=_storage(),
                         dispatch=dispatch_tiles, requeue=requeue)
    return status.value if status else None


@app.task(name=RUN_TILE_TASK, acks_late=True, reject_on_worker_lost=True, ignore_result=False)
def run_tile(job_id: str, cell: list[int], total: int, phase: int | None = None,
             span: tuple[int, int] = (5, 90), round_: int | None = None) -> bool:
    """One tile (or its values for stage ``phase``'s estimate in round ``round_``); its failure
    fails the job with the tile's message, then propagates (so the chord knows)."""
    settings, store, storage = get_settings(), _store(), _storage()
    store.beat([job_id], TILED_HOST)
    try:
        ran = run_job_tile(settings, store, storage, job_id, (int(cell[0]), int(cell[1])),
                           values_of=phase, round_=round_)
    except SoftTimeLimitExceeded:
        fail_tiled_job(store, storage, job_id,
                       f"a tile exceeded the time limit of {settings.task_time_limit} s",
                       settings)
        raise
    except LidarOutliersError as exc:
        fail_tiled_job(store, storage, job_id,
                       f"tile {cell[0]}, {cell[1]}: {disk_full_message(exc) or exc}", settings)
        raise
    except Exception as exc:
        fail_tiled_job(store, storage, job_id, f"tile {cell[0]}, {cell[1]}: "
                       + (disk_full_message(exc) or f"internal error: {type(exc).__name__}: {exc}"),
                       settings)
        raise
    store.beat([job_id], TILED_HOST)
    if ran:
        _count_tile(store, job_id, cell, total, phase, span, round_)
    return ran


def _count_tile(store: Store, job_id: str, cell: list[int], total: int, phase: int | None,
                span: tuple[int, int], round_: int | None = None) -> None:
    client = app.backend.client
    key = _DONE_KEY.format(f"{job_id}:{phase}:{round_}")  # each round counts its own tiles
    client.sadd(key, f"{cell[0]},{cell[1]}")  # a set: a tile run twice counts once
    client.expire(key, get_settings().visibility_timeout)
    done = int(client.scard(key))
    what = "tiles" if phase is None else "estimates"
    store.set_progress(job_id, span[0] + int((span[1] - span[0]) * done / max(total, 1)),
                       f"{what}: tile {done} of {total} done")


@app.task(name=PIN_TILES_TASK, acks_late=True, reject_on_worker_lost=True)
def pin_tiles(job_id: str, phase: int, round_: int | None = None) -> None:
    """Fix the estimate from every tile's values, then queue the next round of tiles."""
    settings, store, storage = get_settings(), _store(), _storage()
    store.beat([job_id], TILED_HOST)
    try:
        pinned = pin_job_stage(settings, store, storage, job_id, phase, round_)
    except LidarOutliersError as exc:
        fail_tiled_job(store, storage, job_id, str(exc))
        raise
    store.beat([job_id], TILED_HOST)
    if pinned:
        dispatch_tiles(job_id, job_cells(storage, job_id))


def _forget_counts(job_id: str) -> None:
    client = app.backend.client
    keys = list(client.scan_iter(_DONE_KEY.format(f"{job_id}:*")))
    if keys:
        client.delete(*keys)


@app.task(name=MERGE_TILES_TASK, acks_late=True, reject_on_worker_lost=True)
def merge_tiles(job_id: str) -> str | None:
    _forget_counts(job_id)
    _store().beat([job_id], TILED_HOST)
    status = merge_job(get_settings(), _store(), _storage(), job_id)
    return status.value if status else None


@app.task(name=TILES_FAILED_TASK)
def tiles_failed(request: Any, exc: BaseException, traceback: Any, job_id: str) -> None:
    """The chord's error callback: the job fails (if a tile has not failed it already) and its
    tiles are removed."""
    _forget_counts(job_id)
    fail_tiled_job(_store(), _storage(), job_id, f"a tile failed: {exc}")
