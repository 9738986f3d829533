"""Jobs whose worker is gone: found by their heartbeat, put back in the queue or failed.

A worker records every ``HEARTBEAT_INTERVAL_SECONDS`` that the jobs it runs are alive
(:meth:`~lidar_outliers.jobs.store.Store.beat`) and then sweeps (:class:`Janitor`): a running job
without a heartbeat for ``STALE_JOB_SECONDS``, or whose worker process on this host no longer
exists, belonged to a worker that was killed with its pool (SIGKILL, out of memory, a lost
host). Such a job is queued again, or failed once it has been started ``MAX_ATTEMPTS`` times;
without this it would wait for the broker's visibility timeout (hours).

A job cut into tiles (``worker_host`` :data:`~lidar_outliers.jobs.store.TILED_HOST`) is held by
no process: its tiles, its merge and the chord's error callback end it, and a tile whose worker
died is delivered again by the broker. Its tile tasks beat for it at their start and end and
the workers running or holding them beat for it in between, but tiles may wait in the queue
without anyone beating, so such a job is only taken back once nothing beat for it for the
broker's ``VISIBILITY_TIMEOUT`` plus ``STALE_JOB_SECONDS`` (its tile messages were all lost):
it then runs again from the start instead of being left running for ever.

Every worker sweeps; :meth:`~lidar_outliers.jobs.store.Store.reclaim` changes a job only as it
was read, so two sweeps never queue one job twice. The new message carries the job's re-queue
count, and a delivery of an older message (Redis re-delivers the dead worker's one after the
visibility timeout) is dropped by :func:`~lidar_outliers.jobs.execute.execute_job`.
"""

from __future__ import annotations

import logging
import socket
from collections.abc import Callable
from datetime import UTC, datetime

import psutil

from lidar_outliers.jobs import layout
from lidar_outliers.jobs.settings import Settings
from lidar_outliers.jobs.storage import Storage, StorageError
from lidar_outliers.jobs.store import TILED_HOST, Job, JobStatus, Store, parse_time

log = logging.getLogger(__name__)

#: ``send(job_id, requeues)`` puts a job in the queue again (the worker's Celery app does).
Send = Callable[[str, int], None]


def died_message(attempts: int) -> str:
    return (f"the worker running this job died {attempts} times (killed, e.g. out of memory); "
            "the job is not retried")


def abandoned(job: Job, *, now: datetime, stale_after: float, host: str,
              tiled_after: float | None = None) -> str | None:
    """Why the worker of a running job is taken for gone, or None while it may still run it.
    ``tiled_after``: the staleness of a job whose tiles run on the workers (default
    ``stale_after``)."""
    last = parse_time(job.heartbeat or job.started or job.created)
    age = (now - last).total_seconds()
    if job.worker_host == TILED_HOST:
        limit = stale_after if tiled_after is None else tiled_after
        return f"its tiles sent no heartbeat for {age:.0f} s" if age > limit else None
    if age > stale_after:
        return f"its worker sent no heartbeat for {age:.0f} s"
    if job.worker_host == host and job.worker_pid and not psutil.pid_exists(job.worker_pid):
        return f"its worker process {job.worker_pid} on {host} is gone"
    return None


class Janitor:
    """Sweeps of one worker. A job re-queued while Redis was unreachable is sent again by the
    next sweep of the same janitor."""

    def __init__(self, settings: Settings, store: Store, storage: Storage, send: Send,
                 host: str | None = None) -> None:
        self.settings = settings
        self.store = store
        self.storage = storage
        self.send = send
        self.host = host or socket.gethostname()
        self.unsent: dict[str, int] = {}

    def sweep(self, now: datetime | None = None) -> list[Job]:
        """Re-queue or fail every running job whose worker is gone; return them as changed."""
        now = now or datetime.now(UTC)
        changed = []
        for job in self.store.running_jobs():
            reason = abandoned(job, now=now, stale_after=self.settings.stale_job_seconds,
                               host=self.host, tiled_after=self.settings.visibility_timeout
                               + self.settings.stale_job_seconds)
            if reason is None:
                continue
            if job.attempts >= self.settings.max_attempts:
                done = self.store.reclaim(job, died_message(job.attempts), give_up=True,
                                          stored_bytes=self._stored_bytes(job.id))
            else:
                done = self.store.reclaim(job, f"queued again: {reason}")
                if done is not None:
                    self.unsent[job.id] = done.requeues
            if done is not None:
                log.warning("job %s: %s; %s", job.id, reason, done.status.value)
                changed.append(done)
        self._send_pending()
        return changed

    def _send_pending(self) -> None:
        for job_id, requeues in list(self.unsent.items()):
            job = self.store.get_job(job_id)
            if job is None or job.status is not JobStatus.accepted or job.requeues != requeues:
                del self.unsent[job_id]  # dismissed, or another sweep took it since
                continue
            try:
                self.send(job_id, requeues)
            except Exception:  # the broker is down: the next sweep tries again
                log.exception("could not queue job %s again", job_id)
                continue
            del self.unsent[job_id]

    def _stored_bytes(self, job_id: str) -> int | None:
        try:
            return self.storage.prefix_bytes(layout.job_prefix(job_id))
        except StorageError:
            log.exception("could not measure the files of job %s", job_id)
            return None
