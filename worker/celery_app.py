"""The Celery application of the workers: ``celery -A worker.celery_app worker``.

Its settings (late acknowledgement, one job per process at a time, priorities, the Redis
visibility timeout, reconnection) are those of :func:`lidar_outliers.jobs.queue.celery_config`,
which the API uses to enqueue. Its main process also beats for its running jobs and re-queues
those of vanished workers (:mod:`worker.watchdog`).
"""

from __future__ import annotations

from celery import Celery

from lidar_outliers.jobs.queue import celery_config
from lidar_outliers.jobs.settings import get_settings
from worker.watchdog import Watchdog


def make_app() -> Celery:
    app = Celery("lidar_outliers", include=["worker.tasks"])
    app.conf.update(celery_config(get_settings()))
    app.steps["worker"].add(Watchdog)  # heartbeats, and jobs of vanished workers re-queued
    return app


app = make_app()
