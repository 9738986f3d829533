"""The worker's heartbeat and janitor: a timer of the worker's main process (not of its pool).

Every ``HEARTBEAT_INTERVAL_SECONDS`` it records that the jobs this worker runs are alive, then
sweeps for running jobs of vanished workers (:class:`lidar_outliers.jobs.janitor.Janitor`) and
queues them again. The main process beats for its pool processes, so a job stuck in a long
computation still beats, and one whose worker was killed (its pool dies with it) stops beating.
It beats too for the tiled jobs whose tile, estimate or merge tasks this worker runs or holds.
"""

from __future__ import annotations

import logging
import socket
from typing import Any

from celery import bootsteps
from celery.worker import state

from lidar_outliers.jobs.janitor import Janitor
from lidar_outliers.jobs.queue import MERGE_TILES_TASK, PIN_TILES_TASK, RUN_JOB_TASK, RUN_TILE_TASK
from lidar_outliers.jobs.settings import get_settings
from lidar_outliers.jobs.storage import open_storage
from lidar_outliers.jobs.store import TILED_HOST, Store

log = logging.getLogger(__name__)
#: Tasks of a tiled job: their first argument is the job's id.
TILE_TASKS = frozenset({RUN_TILE_TASK, PIN_TILES_TASK, MERGE_TILES_TASK})


class Watchdog(bootsteps.StartStopStep):
    """Worker blueprint step: starts the timer once the pool runs, stops it at shutdown."""

    requires = {"celery.worker.components:Pool"}

    def __init__(self, worker: Any, **kwargs: Any) -> None:
        super().__init__(worker, **kwargs)
        self.tref: Any = None
        self.janitor: Janitor | None = None

    def start(self, worker: Any) -> None:
        settings = get_settings()
        self.host = socket.gethostname()
        self.app = worker.app
        self.tref = worker.timer.call_repeatedly(settings.heartbeat_interval_seconds, self.tick,
                                                 priority=10)

    def stop(self, worker: Any) -> None:
        if self.tref is not None:
            self.tref.cancel()
            self.tref = None
        if self.janitor is not None:
            self.janitor.store.close()

    def tick(self) -> None:
        try:
            janitor = self._janitor()
            running = [request.id for request in list(state.active_requests)]
            janitor.store.beat(running, self.host)
            janitor.store.beat(tiled_jobs(), TILED_HOST)
            janitor.sweep()
        except Exception:  # the database may be away for a moment: the next tick tries again
            log.exception("heartbeat or sweep failed")

    def _janitor(self) -> Janitor:
        if self.janitor is None:  # made on first use, in the main process, after the fork
            settings = get_settings()
            self.janitor = Janitor(settings, Store(settings.database_url, migrate=False),
                                   open_storage(settings), self._send, self.host)
        return self.janitor

    def _send(self, job_id: str, requeues: int) -> None:
        # first in the queue: the job was running already
        self.app.send_task(RUN_JOB_TASK, args=[job_id], kwargs={"requeue": requeues},
                           task_id=job_id, priority=0)


def tiled_jobs() -> list[str]:
    """The jobs of the tile tasks this worker runs or holds (prefetched)."""
    jobs = set()
    for request in list(state.active_requests) + list(state.reserved_requests):
        if request.name in TILE_TASKS and request.args:
            jobs.add(str(request.args[0]))
    return sorted(jobs)
