"""The Celery application of the workers: ``celery -A worker.celery_app worker``.

Its settings (late acknowledgement, one job per process at a time, priorities, the Redis
visibility timeout) are those of :func:`lidar_outliers.jobs.queue.celery_config`, which the API
uses to enqueue.
"""

from __future__ import annotations

from celery import Celery

from lidar_outliers.jobs.queue import celery_config
from lidar_outliers.jobs.settings import get_settings


def make_app() -> Celery:
    app = Celery("lidar_outliers", include=["worker.tasks"])
    app.conf.update(celery_config(get_settings()))
    return app


app = make_app()
