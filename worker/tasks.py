"""The one Celery task: run a job's pipeline over its input and record the outcome.

:func:`execute_job` holds the logic and is callable without Celery. The job's state changes go
through :meth:`service.store.Store.transition` only.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import time
from pathlib import Path

from celery.exceptions import SoftTimeLimitExceeded

from service.settings import Settings, get_settings
from service.store import FINAL, JobStatus, Store
from worker.celery_app import app
from worker.errors import CancelledError, LidarOutliersError
from worker.params import PipelineParams

log = logging.getLogger(__name__)

#: Write progress to the store at most this often (seconds) unless the percentage changes.
PROGRESS_INTERVAL = 0.5


def job_dir(settings: Settings, job_id: str) -> Path:
    return settings.jobs_dir / job_id


def input_path(settings: Settings, job_id: str, laz: bool) -> Path:
    return job_dir(settings, job_id) / ("input.laz" if laz else "input.las")


def result_path(settings: Settings, job_id: str, laz: bool) -> Path:
    return job_dir(settings, job_id) / ("result.laz" if laz else "result.las")


def statistics_path(settings: Settings, job_id: str) -> Path:
    return job_dir(settings, job_id) / "statistics.json"


def trajectory_path(settings: Settings, job_id: str) -> Path:
    """The job's optional trajectory file (multipart part ``trajectory``)."""
    return job_dir(settings, job_id) / "trajectory.txt"


def folder_bytes(folder: Path) -> int:
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())


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


def _write_json(path: Path, data: dict) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(data, indent=2, default=str))
    os.replace(tmp, path)


def execute_job(settings: Settings, store: Store, job_id: str) -> JobStatus | None:
    """Run one delivery of a job; return its final status (None when there was nothing to do)."""
    job = store.get_job(job_id)
    if job is None or job.status in FINAL:
        return None  # dismissed (or deleted by retention) before a worker got to it
    folder = job_dir(settings, job_id)
    if job.status is JobStatus.running and job.attempts >= settings.max_attempts:
        # every earlier delivery died with its worker (SIGKILL, out of memory): give up
        store.transition(
            job_id, JobStatus.failed,
            f"the worker running this job died {job.attempts} times (killed, e.g. out of "
            "memory); the job is not retried",
            stored_bytes=folder_bytes(folder) if folder.exists() else 0,
        )
        return JobStatus.failed
    started = store.transition(job_id, JobStatus.running, "reading the cloud",
                               worker_pid=os.getpid())
    if started is None:
        return None
    try:
        from worker.pipeline import process_file  # heavy import (numba) only in the worker

        params = PipelineParams.model_validate(job.inputs)
        trajectory = trajectory_path(settings, job_id)
        stats = process_file(
            input_path(settings, job_id, job.laz),
            result_path(settings, job_id, job.laz),
            params,
            laz=job.laz,
            progress=Progress(store, job_id),
            trajectory=trajectory if trajectory.exists() else None,
        )
        if isinstance(stats.get("input"), dict):  # the user's file name, not input.las
            stats["input"]["name"] = job.facts.get("name", stats["input"].get("name"))
        if isinstance(stats.get("trajectory"), dict) and "trajectory" in job.facts:
            stats["trajectory"]["name"] = job.facts["trajectory"].get("name")
        _write_json(statistics_path(settings, job_id), stats)
    except CancelledError:
        shutil.rmtree(folder, ignore_errors=True)
        if store.status(job_id) is JobStatus.dismissed:
            store.annotate(job_id, "dismissed by the user; the worker stopped the running job")
        return JobStatus.dismissed
    except LidarOutliersError as exc:
        return _fail(store, job_id, folder, str(exc))
    except MemoryError:
        return _fail(store, job_id, folder, "the job ran out of memory")
    except SoftTimeLimitExceeded:
        return _fail(store, job_id, folder,
                     f"the job exceeded the time limit of {settings.task_time_limit} s")
    except Exception as exc:
        log.exception("job %s failed", job_id)
        return _fail(store, job_id, folder, f"internal error: {type(exc).__name__}: {exc}")
    done = store.transition(job_id, JobStatus.successful, "done",
                            stored_bytes=folder_bytes(folder))
    if done is None:  # dismissed while the result was being written
        shutil.rmtree(folder, ignore_errors=True)
        return JobStatus.dismissed
    return JobStatus.successful


def _fail(store: Store, job_id: str, folder: Path, message: str) -> JobStatus:
    if store.status(job_id) is JobStatus.dismissed:
        # the error came from the dismissal itself (e.g. the API removed the folder)
        shutil.rmtree(folder, ignore_errors=True)
        store.annotate(job_id, "dismissed by the user; the worker stopped the running job")
        return JobStatus.dismissed
    for name in ("result.las", "result.laz", "statistics.json"):
        (folder / name).unlink(missing_ok=True)
    store.transition(job_id, JobStatus.failed, message,
                     stored_bytes=folder_bytes(folder) if folder.exists() else 0)
    return JobStatus.failed


@app.task(name="lidar_outliers.run_job", acks_late=True, reject_on_worker_lost=True)
def run_job(job_id: str) -> str | None:
    settings = get_settings()
    status = execute_job(settings, Store(settings.db_path), job_id)
    return status.value if status else None
