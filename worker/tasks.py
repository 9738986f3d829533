"""The Celery task: one delivery of a job (:func:`~lidar_outliers.jobs.execute.execute_job`).

The database schema is migrated once when the worker starts (before its pool forks); each pool
process then opens its own store and storage client on its first job.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Any

from celery.exceptions import SoftTimeLimitExceeded
from celery.signals import worker_init

from lidar_outliers.jobs.execute import execute_job
from lidar_outliers.jobs.queue import RUN_JOB_TASK
from lidar_outliers.jobs.settings import get_settings
from lidar_outliers.jobs.storage import Storage, open_storage
from lidar_outliers.jobs.store import Store
from worker.celery_app import app


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


@app.task(name=RUN_JOB_TASK, acks_late=True, reject_on_worker_lost=True)
def run_job(job_id: str, requeue: int = 0) -> str | None:
    """``requeue``: the job's re-queue count when the message was sent (0 from the API)."""
    status = execute_job(get_settings(), _store(), job_id,
                         time_limit_errors=(SoftTimeLimitExceeded,), storage=_storage(),
                         requeue=requeue)
    return status.value if status else None
