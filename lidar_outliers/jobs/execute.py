"""One delivery of a job: run its pipeline over its input and record the outcome.

:func:`execute_job` is the whole run, callable without Celery (the worker's task calls it). The
job's state changes go through :meth:`lidar_outliers.jobs.store.Store.transition` only.
"""

from __future__ import annotations

import logging
import os
import shutil
import time
from pathlib import Path

from lidar_outliers.atomic import write_json_atomic
from lidar_outliers.errors import CancelledError, LidarOutliersError
from lidar_outliers.jobs import layout
from lidar_outliers.jobs.settings import Settings
from lidar_outliers.jobs.store import FINAL, JobStatus, Store
from lidar_outliers.params import PipelineParams

log = logging.getLogger(__name__)

#: Write progress to the store at most this often (seconds) unless the percentage changes.
PROGRESS_INTERVAL = 0.5
DISMISSED_WHILE_RUNNING = "dismissed by the user; the worker stopped the running job"


class Progress:
    """The ``progress(fraction, message)`` callback of ``process_file``: records progress and
    raises :class:`CancelledError` once the job has been dismissed (DELETE /jobs/{id})."""

    def __init__(self, store: Store, job_id: str) -> None:
        self.store = store
        self.job_id = job_id
        self._last_time = 0.0
        self._last_percent = -1

    def __call__(self, fraction: float, message: str) -> None:
        percent = int(max(0.0, min(1.0, float(fraction))) * 100)
        now = time.monotonic()
        if percent == self._last_percent and now - self._last_time < PROGRESS_INTERVAL:
            return
        self._last_time, self._last_percent = now, percent
        status = self.store.set_progress(self.job_id, percent, message)
        if status is not JobStatus.running:
            raise CancelledError("the job was dismissed")


def execute_job(
    settings: Settings, store: Store, job_id: str,
    time_limit_errors: tuple[type[BaseException], ...] = (),
) -> JobStatus | None:
    """Run one delivery of a job; return its final status (None when there was nothing to do).

    ``time_limit_errors``: exceptions that mean the job ran out of time (the queue's own soft
    time limit); the job then fails with a message naming the limit.
    """
    job = store.get_job(job_id)
    if job is None or job.status in FINAL:
        return None  # dismissed (or deleted by retention) before a worker got to it
    folder = layout.job_dir(settings, job_id)
    if job.status is JobStatus.running and job.attempts >= settings.max_attempts:
        # every earlier delivery died with its worker (SIGKILL, out of memory): give up
        store.transition(
            job_id, JobStatus.failed,
            f"the worker running this job died {job.attempts} times (killed, e.g. out of "
            "memory); the job is not retried",
            stored_bytes=layout.folder_bytes(folder) if folder.exists() else 0,
        )
        return JobStatus.failed
    started = store.transition(job_id, JobStatus.running, "reading the cloud",
                               worker_pid=os.getpid())
    if started is None:
        return None
    try:
        _run(settings, store, job_id)
    except CancelledError:
        shutil.rmtree(folder, ignore_errors=True)
        if store.status(job_id) is JobStatus.dismissed:
            store.annotate(job_id, DISMISSED_WHILE_RUNNING)
        return JobStatus.dismissed
    except LidarOutliersError as exc:
        return _fail(store, job_id, folder, str(exc))
    except MemoryError:
        return _fail(store, job_id, folder, "the job ran out of memory")
    except time_limit_errors:
        return _fail(store, job_id, folder,
                     f"the job exceeded the time limit of {settings.task_time_limit} s")
    except Exception as exc:
        log.exception("job %s failed", job_id)
        return _fail(store, job_id, folder, f"internal error: {type(exc).__name__}: {exc}")
    done = store.transition(job_id, JobStatus.successful, "done",
                            stored_bytes=layout.folder_bytes(folder))
    if done is None:  # dismissed while the result was being written
        shutil.rmtree(folder, ignore_errors=True)
        return JobStatus.dismissed
    return JobStatus.successful


def _run(settings: Settings, store: Store, job_id: str) -> None:
    """The pipeline over the job's input; the statistics name the user's files."""
    from lidar_outliers.process import process_file  # heavy imports (numba) only when run

    job = store.get_job(job_id)
    assert job is not None
    params = PipelineParams.model_validate(job.inputs)
    trajectory = layout.trajectory_path(settings, job_id)
    stats = process_file(
        layout.input_path(settings, job_id, job.laz),
        layout.result_path(settings, job_id, job.laz),
        params,
        laz=job.laz,
        progress=Progress(store, job_id),
        trajectory=trajectory if trajectory.exists() else None,
    )
    if isinstance(stats.get("input"), dict):  # the user's file name, not input.las
        stats["input"]["name"] = job.facts.get("name", stats["input"].get("name"))
    if isinstance(stats.get("trajectory"), dict) and "trajectory" in job.facts:
        stats["trajectory"]["name"] = job.facts["trajectory"].get("name")
    write_json_atomic(layout.statistics_path(settings, job_id), stats)


def _fail(store: Store, job_id: str, folder: Path, message: str) -> JobStatus:
    if store.status(job_id) is JobStatus.dismissed:
        # the error came from the dismissal itself (e.g. the API removed the folder)
        shutil.rmtree(folder, ignore_errors=True)
        store.annotate(job_id, DISMISSED_WHILE_RUNNING)
        return JobStatus.dismissed
    for name in layout.RESULT_NAMES:
        (folder / name).unlink(missing_ok=True)
    store.transition(job_id, JobStatus.failed, message,
                     stored_bytes=layout.folder_bytes(folder) if folder.exists() else 0)
    return JobStatus.failed
