"""The API's side of the job queue: enqueue by task name and ping the workers.

The API never imports the worker package; it sends :data:`RUN_JOB_TASK` by name through a
Celery client configured like the workers (:func:`lidar_outliers.jobs.queue.celery_config`).
"""

from __future__ import annotations

from functools import lru_cache

from celery import Celery

from lidar_outliers.jobs.queue import LOWEST_PRIORITY, RUN_JOB_TASK, celery_config
from lidar_outliers.jobs.settings import Settings, get_settings


@lru_cache
def client(redis_url: str | None = None) -> Celery:
    """A Celery app used only to send tasks and control messages (no task is registered)."""
    settings = get_settings()
    config = celery_config(settings)
    if redis_url is not None:
        config["broker_url"] = redis_url
    app = Celery("lidar_outliers")
    app.conf.update(config)
    return app


def enqueue(settings: Settings, job_id: str, priority: int) -> None:
    """Queue a job for the workers; ``priority`` 0 is taken first (Redis transport)."""
    client(settings.redis_url).send_task(
        RUN_JOB_TASK, args=[job_id], task_id=job_id,
        priority=max(0, min(priority, LOWEST_PRIORITY)),
    )


def ping_workers(settings: Settings, timeout: float = 1.0) -> list[str]:
    """Names of the workers that answered a ping within ``timeout`` seconds."""
    replies = client(settings.redis_url).control.ping(timeout=timeout) or []
    return sorted(name for reply in replies for name in reply)
