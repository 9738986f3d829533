"""The job queue's contract: the task's name and the Celery settings both sides must share.

The API enqueues by task name (it never imports the worker); the worker registers its task under
the same name. Both build their Celery app from :func:`celery_config`, so priorities and the
Redis transport options agree.

Settings that make a job survive a dying worker:
- ``task_acks_late`` + ``task_reject_on_worker_lost``: the message is acknowledged only after the
  job ends, and re-queued when the process running it is killed (SIGKILL, out of memory);
- ``worker_prefetch_multiplier = 1``: a busy worker holds no further jobs another could run;
- the broker's ``visibility_timeout`` is longer than the hard time limit, so Redis re-delivers a
  job whose whole worker vanished only once that job cannot still be running; well before that,
  the workers' heartbeats and sweeps (:mod:`lidar_outliers.jobs.janitor`) queue it again;
- priorities 0-9 (0 first) let the API queue a user's n-th active job behind other users' first
  jobs (fairness).

The tiles of a large job are a chord (a group of tile tasks, then the merge), which needs a
result backend: Redis again. Its results live as long as the retention of jobs, so a chord
whose tiles take long (many tiles, few workers) still completes; only the tile tasks keep a
result.
"""

from __future__ import annotations

from typing import Any

from lidar_outliers.jobs.settings import Settings

#: Run a job's pipeline over its input (argument: the job id); a large job is cut into tiles.
RUN_JOB_TASK = "lidar_outliers.run_job"
#: One tile of a job cut into tiles (job id, cell), the merge of its tiles (job id), and the
#: error callback that fails the job when a tile or the merge failed.
RUN_TILE_TASK = "lidar_outliers.run_tile"
MERGE_TILES_TASK = "lidar_outliers.merge_tiles"
#: Fixes a parameter estimated from the whole cloud (job id, stage) from the tiles' values.
PIN_TILES_TASK = "lidar_outliers.pin_tiles"
TILES_FAILED_TASK = "lidar_outliers.tiles_failed"
PRIORITY_STEPS = list(range(10))
#: Priority of a user's n-th active job (capped at the lowest priority).
LOWEST_PRIORITY = PRIORITY_STEPS[-1]


def celery_config(settings: Settings) -> dict[str, Any]:
    """Celery settings of the API (producer) and the workers (consumers) alike."""
    return dict(
        broker_url=settings.redis_url,
        task_acks_late=True,
        task_reject_on_worker_lost=True,
        worker_prefetch_multiplier=1,
        task_ignore_result=True,
        result_backend=settings.redis_url,
        result_expires=int(settings.retention_days * 86400) + settings.visibility_timeout,
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
        # Redis restarted or away for a while: keep reconnecting (never give up), and a task
        # being sent waits for it a few seconds before the API answers 503
        broker_connection_retry_on_startup=True,
        broker_connection_retry=True,
        broker_connection_max_retries=None,
        task_publish_retry_policy={"max_retries": 6, "interval_start": 0.2,
                                   "interval_step": 0.5, "interval_max": 1.5},
        worker_cancel_long_running_tasks_on_connection_loss=True,
        # On SIGTERM/Ctrl-C: give a running job a few seconds, then re-queue it (Redis) and stop.
        worker_soft_shutdown_timeout=5.0,
        worker_enable_soft_shutdown_on_idle=True,
        worker_hijack_root_logger=False,
    )
