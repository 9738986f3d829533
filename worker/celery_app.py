"""The Celery application: Redis broker, late acknowledgement, one job per worker process at a time.

Settings that make a job survive a dying worker:
- ``task_acks_late`` + ``task_reject_on_worker_lost``: the message is acknowledged only after the
  job ends, and re-queued when the process running it is killed (SIGKILL, out of memory);
- ``worker_prefetch_multiplier = 1``: a busy worker holds no further jobs another could run;
- the broker's ``visibility_timeout`` is longer than the hard time limit, so Redis re-delivers a
  job whose whole worker vanished only once that job cannot still be running;
- priorities 0-9 (0 first) let the API queue a user's n-th active job behind other users' first
  jobs (fairness; see ``service.jobs.JobService.submit``).
"""

from __future__ import annotations

from celery import Celery

from service.settings import get_settings

PRIORITY_STEPS = list(range(10))


def make_app() -> Celery:
    settings = get_settings()
    app = Celery("lidar_outliers", broker=settings.redis_url, include=["worker.tasks"])
    app.conf.update(
        task_acks_late=True,
        task_reject_on_worker_lost=True,
        worker_prefetch_multiplier=1,
        task_ignore_result=True,
        task_serializer="json",
        accept_content=["json"],
        task_time_limit=settings.task_time_limit,
        task_soft_time_limit=settings.soft_time_limit,
        task_default_priority=0,
        broker_transport_options={
            "visibility_timeout": settings.visibility_timeout,
            "priority_steps": PRIORITY_STEPS,
            # sweep for jobs of vanished workers every 5 s (kombu's default is every 100 s);
            # a sweep re-queues only jobs older than the visibility timeout
            "unacked_restore_interval": 5,
            "unacked_restore_throttle": 1,
        },
        broker_connection_retry_on_startup=True,
        worker_cancel_long_running_tasks_on_connection_loss=True,
        # On SIGTERM/Ctrl-C: give a running job a few seconds, then re-queue it (Redis) and stop.
        worker_soft_shutdown_timeout=5.0,
        worker_enable_soft_shutdown_on_idle=True,
        worker_hijack_root_logger=False,
    )
    return app


app = make_app()
