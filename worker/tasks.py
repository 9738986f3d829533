"""The Celery task: one delivery of a job (:func:`~lidar_outliers.jobs.execute.execute_job`)."""

from __future__ import annotations

from celery.exceptions import SoftTimeLimitExceeded

from lidar_outliers.jobs.execute import execute_job
from lidar_outliers.jobs.queue import RUN_JOB_TASK
from lidar_outliers.jobs.settings import get_settings
from lidar_outliers.jobs.store import Store
from worker.celery_app import app


@app.task(name=RUN_JOB_TASK, acks_late=True, reject_on_worker_lost=True)
def run_job(job_id: str) -> str | None:
    settings = get_settings()
    status = execute_job(settings, Store(settings.db_path), job_id,
                         time_limit_errors=(SoftTimeLimitExceeded,))
    return status.value if status else None
