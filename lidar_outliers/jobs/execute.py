"""One delivery of a job: run its pipeline over its input and record the outcome.

:func:`execute_job` is the whole run, callable without Celery (the worker's task calls it). The
job's state changes go through :meth:`lidar_outliers.jobs.store.Store.transition` only. The
input is copied from the storage to a local scratch folder, the pipeline runs there, and the
result and the statistics are put back; the scratch folder is removed whatever happens.
"""

from __future__ import annotations

import logging
import os
import shutil
import socket
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TypeVar

from lidar_outliers.atomic import write_json_atomic
from lidar_outliers.errors import CancelledError, LidarOutliersError
from lidar_outliers.jobs import layout
from lidar_outliers.jobs.callbacks import FAILED, IN_PROGRESS, SUCCESS, deliver
from lidar_outliers.jobs.diskspace import is_disk_full
from lidar_outliers.jobs.documents import results_document, status_document
from lidar_outliers.jobs.janitor import died_message
from lidar_outliers.jobs.settings import Settings
from lidar_outliers.jobs.storage import Storage, StorageError, open_storage
from lidar_outliers.jobs.store import FINAL, Job, JobStatus, Store
from lidar_outliers.params import PipelineParams

log = logging.getLogger(__name__)
T = TypeVar("T")
#: Hands a job's tiles to the queue: ``dispatch(job_id, cells)`` (the worker's chord).
Dispatch = Callable[[str, Sequence[tuple[int, int]]], None]

#: Write progress to the store at most this often (seconds) unless the percentage changes.
PROGRESS_INTERVAL = 0.5
DISMISSED_WHILE_RUNNING = "dismissed by the user; the worker stopped the running job"


class Superseded(CancelledError):
    """This delivery's job was taken back (its worker looked gone) and queued again."""


class Progress:
    """The ``progress(fraction, message)`` callback of ``process_file``: records progress and
    raises :class:`CancelledError` once the job has been dismissed (DELETE /jobs/{id}), or
    :class:`Superseded` once another delivery has it."""

    def __init__(self, store: Store, job_id: str, attempt: int | None = None) -> None:
        self.store = store
        self.job_id = job_id
        self.attempt = attempt
        self._last_time = 0.0
        self._last_percent = -1

    def __call__(self, fraction: float, message: str) -> None:
        percent = int(max(0.0, min(1.0, float(fraction))) * 100)
        now = time.monotonic()
        if percent == self._last_percent and now - self._last_time < PROGRESS_INTERVAL:
            return
        self._last_time, self._last_percent = now, percent
        status = self.store.set_progress(self.job_id, percent, message, self.attempt)
        if status is None or status is JobStatus.accepted:
            raise Superseded("the job was queued again")
        if status is not JobStatus.running:
            raise CancelledError("the job was dismissed")


def execute_job(
    settings: Settings, store: Store, job_id: str,
    time_limit_errors: tuple[type[BaseException], ...] = (),
    storage: Storage | None = None,
    dispatch: Dispatch | None = None,
    requeue: int = 0,
) -> JobStatus | None:
    """Run one delivery of a job; return its final status (None when there was nothing to do).

    ``dispatch``: with it a job of more than ``TILE_JOB_POINTS`` points is cut into tiles that
    any worker may run (:mod:`lidar_outliers.jobs.tiles`); the job is then still running when
    this returns (``JobStatus.running``) and the merge of its tiles ends it.
    ``requeue``: the job's re-queue count when this message was sent
    (:mod:`lidar_outliers.jobs.janitor`); a message older than the job's latest re-queue is
    dropped, so a job runs once however many of its messages Redis delivers.
    ``time_limit_errors``: exceptions that mean the job ran out of time (the queue's own soft
    time limit); the job then fails with a message naming the limit. ``storage``: where the
    job's objects are (default: the one the settings name). The job's subscriber hears of its
    start and of its success or failure.
    """
    status = _execute(settings, store, job_id, time_limit_errors, storage, requeue, dispatch)
    if status in (JobStatus.successful, JobStatus.failed):
        job = store.get_job(job_id)
        if job is not None:
            notify(settings, job, SUCCESS if status is JobStatus.successful else FAILED)
    return status


def notify(settings: Settings, job: Job, which: str) -> bool:
    """POST the job's document to its subscriber's ``which`` URI, if it gave one: the results
    document on success, the status document otherwise. Never raises: a callback does not
    change the job's outcome."""
    uri = (job.subscriber or {}).get(which)
    if not uri:
        return False
    base_url = (job.subscriber or {}).get("base_url", "")
    try:
        document = (results_document(job, base_url) if which == SUCCESS
                    else status_document(job, base_url))
        return deliver(uri, document, settings.callback_allow_list)
    except Exception:  # a callback must never take the worker down
        log.exception("callback %s of job %s failed", which, job.id)
        return False


def _execute(
    settings: Settings, store: Store, job_id: str,
    time_limit_errors: tuple[type[BaseException], ...],
    storage: Storage | None,
    requeue: int,
    dispatch: Dispatch | None,
) -> JobStatus | None:
    storage = storage or open_storage(settings)
    job = store.get_job(job_id)
    if job is None or job.status in FINAL:
        return None  # dismissed (or deleted by retention) before a worker got to it
    if job.requeues != requeue:
        return None  # queued again since this message was sent: that newer message runs it
    prefix = layout.job_prefix(job_id)
    if job.status is JobStatus.running and job.attempts >= settings.max_attempts:
        # every earlier delivery died with its worker (SIGKILL, out of memory): give up
        store.transition(job_id, JobStatus.failed, died_message(job.attempts),
                         stored_bytes=quietly(storage.prefix_bytes, prefix))
        return JobStatus.failed
    started = store.transition(job_id, JobStatus.running, "reading the cloud",
                               worker_pid=os.getpid(), worker_host=socket.gethostname(),
                               requeues=requeue)
    if started is None:
        return None
    notify(settings, started, IN_PROGRESS)
    # folders of deliveries killed on this host: older than any job may run
    layout.sweep_scratch(settings, older_than=settings.visibility_timeout)
    scratch = layout.scratch(settings, f"job-{job_id}")
    try:
        stored = _run(settings, store, storage, started, scratch, dispatch)
    except Superseded:
        return None  # the job's files are the newer delivery's now
    except CancelledError:
        quietly(storage.delete_prefix, prefix)
        if store.status(job_id) is JobStatus.dismissed:
            store.annotate(job_id, DISMISSED_WHILE_RUNNING)
        return JobStatus.dismissed
    except LidarOutliersError as exc:
        return fail_job(store, storage, job_id, disk_full_message(exc) or str(exc),
                        started.attempts)
    except MemoryError:
        return fail_job(store, storage, job_id, "the job ran out of memory", started.attempts)
    except time_limit_errors:
        return fail_job(store, storage, job_id,
                        f"the job exceeded the time limit of {settings.task_time_limit} s",
                        started.attempts)
    except Exception as exc:
        message = disk_full_message(exc)
        if message is None:
            log.exception("job %s failed", job_id)
            message = f"internal error: {type(exc).__name__}: {exc}"
        return fail_job(store, storage, job_id, message, started.attempts)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    if stored is None:
        return JobStatus.running  # the tiles run on the workers; the merge ends the job
    done = store.transition(job_id, JobStatus.successful, "done", stored_bytes=stored)
    if done is None:
        if store.status(job_id) is not JobStatus.dismissed:
            return None  # another delivery of the job ended it first; its files stay
        quietly(storage.delete_prefix, prefix)  # dismissed while the result was written
        return JobStatus.dismissed
    return JobStatus.successful


def _run(settings: Settings, store: Store, storage: Storage, job: Job,
         scratch: Path, dispatch: Dispatch | None = None) -> int | None:
    """The pipeline over a local copy of the job's input; the statistics name the user's
    files. The result and the statistics are put into the storage when both are complete.
    Returns the bytes the job now keeps, or None when its tiles were handed to the queue."""
    from lidar_outliers.process import process_file  # heavy imports (numba) only when run

    job_id, attempt = job.id, job.attempts
    params = PipelineParams.model_validate(job.inputs)
    suffix = ".laz" if job.laz else ".las"
    source, result = scratch / f"input{suffix}", scratch / f"result{suffix}"
    stored = storage.get_file(layout.input_key(job_id, job.laz), source)
    trajectory = None
    if "trajectory" in job.facts:
        trajectory = scratch / "trajectory.txt"
        stored += storage.get_file(layout.trajectory_key(job_id), trajectory)
    if dispatch is not None:
        from lidar_outliers.jobs.tiles import split_job

        cells = split_job(settings, store, storage, job_id, source, scratch,
                          Progress(store, job_id, attempt))
        if cells:
            # from here the tiles keep the job's heartbeat, not this process
            if not store.hand_to_tiles(job_id, attempt):
                raise Superseded("the job was queued again")
            store.set_progress(job_id, 5, f"{len(cells)} tiles queued")
            dispatch(job_id, cells)
            return None
    stats = process_file(
        source,
        result,
        params,
        laz=job.laz,
        progress=Progress(store, job_id, attempt),
        trajectory=trajectory,
    )
    if isinstance(stats.get("input"), dict):  # the user's file name, not input.las
        stats["input"]["name"] = job.facts.get("name", stats["input"].get("name"))
    if isinstance(stats.get("trajectory"), dict) and "trajectory" in job.facts:
        stats["trajectory"]["name"] = job.facts["trajectory"].get("name")
    statistics = scratch / "statistics.json"
    write_json_atomic(statistics, stats)
    stored += storage.put_file(layout.result_key(job_id, job.laz), result, move=True)
    stored += storage.put_file(layout.statistics_key(job_id), statistics, move=True)
    return stored


def disk_full_message(exc: BaseException) -> str | None:
    """The failure message of a job whose files did not fit on the disk (None otherwise)."""
    if not is_disk_full(exc):
        return None
    log.warning("job failed: disk full: %s", exc)
    return f"the server's disk is full: no room for the job's files ({exc}); submit it again " \
        "later"


def fail_job(store: Store, storage: Storage, job_id: str, message: str,
             attempt: int | None = None) -> JobStatus | None:
    """Record the job as failed with ``message`` and remove any part of its result. With
    ``attempt``, only delivery ``attempt`` may: not when the job is no longer its own."""
    prefix = layout.job_prefix(job_id)
    job = store.get_job(job_id)
    if job is not None and job.status is JobStatus.dismissed:
        # the error came from the dismissal itself (e.g. the API removed the objects)
        quietly(storage.delete_prefix, prefix)
        store.annotate(job_id, DISMISSED_WHILE_RUNNING)
        return JobStatus.dismissed
    if job is None or job.status is not JobStatus.running or (
            attempt is not None and job.attempts != attempt):
        return None  # queued again or started by another delivery since: its outcome counts
    for name in layout.RESULT_NAMES:
        quietly(storage.delete, prefix + name)
    # the storage may be what failed: the job is recorded as failed all the same
    stored = quietly(storage.prefix_bytes, prefix)
    store.transition(job_id, JobStatus.failed, message, stored_bytes=stored)
    return JobStatus.failed


def quietly(action: Callable[[str], T], key: str) -> T | None:
    """Clean-up that must not hide the outcome being recorded: storage errors are logged."""
    try:
        return action(key)
    except StorageError:
        log.exception("storage clean-up of %s failed", key)
        return None
