"""Jobs of vanished workers, on SQLite and PostgreSQL: found by an old heartbeat or a gone
process, queued again once however many workers sweep, failed after MAX_ATTEMPTS starts; a
delivery older than the last re-queue neither starts nor reports. Time is passed to the sweep,
not waited for."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest

from lidar_outliers.jobs.execute import execute_job
from lidar_outliers.jobs.janitor import Janitor
from lidar_outliers.jobs.settings import Settings
from lidar_outliers.jobs.storage import open_storage
from lidar_outliers.jobs.store import TILED_HOST, Job, JobStatus, Store

HOST = socket.gethostname()


@pytest.fixture
def settings(tmp_path: Path, database_url: str) -> Settings:
    return Settings(data_dir=tmp_path, database_url=database_url, heartbeat_interval_seconds=1,
                    stale_job_seconds=5, max_attempts=2)


class Queue:
    """What the janitor sends (the worker's Celery app in service); ``down`` refuses like an
    unreachable Redis."""

    def __init__(self) -> None:
        self.sent: list[tuple[str, int]] = []
        self.down = False

    def __call__(self, job_id: str, requeues: int) -> None:
        if self.down:
            raise ConnectionError("Redis is not reachable")
        self.sent.append((job_id, requeues))


def janitor(settings: Settings, store: Store, queue: Queue) -> Janitor:
    return Janitor(settings, store, open_storage(settings), queue, host=HOST)


def running_job(store: Store, pid: int | None = None, starts: int = 1) -> Job:
    user, _ = store.add_user(f"u{os.urandom(4).hex()}")
    job = store.create_job(user.id, "temporal", {"pipeline": None}, {"points": 10}, False, 100)
    for _ in range(starts):
        started = store.transition(job.id, JobStatus.running, "reading",
                                   worker_pid=pid or os.getpid(), worker_host=HOST)
    assert started is not None and started.heartbeat
    return started


def later(seconds: float) -> datetime:
    return datetime.now(UTC) + timedelta(seconds=seconds)


def gone_pid() -> int:
    """The pid of a process that has exited."""
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_a_job_without_heartbeat_is_queued_again_once(settings: Settings, store: Store) -> None:
    job = running_job(store)
    queue = Queue()
    assert janitor(settings, store, queue).sweep(now=later(1)) == []  # beat a second ago
    first, second = janitor(settings, store, queue), janitor(settings, store, queue)
    changed = first.sweep(now=later(10))
    assert [(j.id, j.status, j.requeues) for j in changed] == [(job.id, JobStatus.accepted, 1)]
    assert second.sweep(now=later(10)) == []  # another worker's sweep finds nothing to do
    assert queue.sent == [(job.id, 1)]
    stored = store.get_job(job.id)
    assert stored.worker_pid is None and stored.progress == 0
    assert stored.message.startswith("queued again: its worker sent no heartbeat for")


def test_a_beating_job_stays_and_a_gone_process_is_noticed_at_once(settings: Settings,
                                                                   store: Store) -> None:
    live, dead = running_job(store), running_job(store, pid=gone_pid())
    queue = Queue()
    assert store.beat([live.id, dead.id], HOST) == 2
    assert store.beat([live.id], "another-host") == 0  # not the host running it
    changed = janitor(settings, store, queue).sweep()
    assert [j.id for j in changed] == [dead.id]
    assert "is gone" in changed[0].message
    assert store.get_job(live.id).status is JobStatus.running
    # on another host the pid means nothing: only the heartbeat counts there
    elsewhere = running_job(store, pid=gone_pid())
    assert Janitor(settings, store, open_storage(settings), queue,
                   host="another-host").sweep() == []
    assert store.get_job(elsewhere.id).status is JobStatus.running


def test_after_max_attempts_the_job_fails(settings: Settings, store: Store) -> None:
    job = running_job(store, starts=2)
    queue = Queue()
    changed = janitor(settings, store, queue).sweep(now=later(10))
    assert [(j.id, j.status) for j in changed] == [(job.id, JobStatus.failed)]
    assert "died 2 times" in changed[0].message and changed[0].finished
    assert queue.sent == []


def test_reclaim_changes_only_the_job_as_read(store: Store) -> None:
    job = running_job(store)
    store.transition(job.id, JobStatus.running, "again", worker_pid=1, worker_host=HOST)
    assert store.reclaim(job, "queued again") is None  # it started again since it was read
    assert store.get_job(job.id).status is JobStatus.running


def test_a_requeue_sent_while_redis_is_down_is_sent_by_the_next_sweep(settings: Settings,
                                                                      store: Store) -> None:
    job = running_job(store)
    queue = Queue()
    queue.down = True
    sweeper = janitor(settings, store, queue)
    assert len(sweeper.sweep(now=later(10))) == 1
    assert queue.sent == [] and store.get_job(job.id).status is JobStatus.accepted
    queue.down = False
    assert sweeper.sweep(now=later(11)) == []
    assert queue.sent == [(job.id, 1)]


def test_an_older_delivery_neither_starts_nor_reports(settings: Settings, store: Store) -> None:
    job = running_job(store)
    janitor(settings, store, Queue()).sweep(now=later(10))
    # the old delivery still runs somewhere: its progress is refused, so it stops
    assert store.set_progress(job.id, 40, "stage 1/2", attempt=1) is JobStatus.accepted
    # the dead worker's message, delivered again by Redis, does not start the job
    assert execute_job(settings, store, job.id, requeue=0) is None
    assert store.get_job(job.id).attempts == 1
    # the new message's delivery starts it (attempt 2); the old one can no longer report
    again = store.transition(job.id, JobStatus.running, "reading", worker_pid=os.getpid(),
                             worker_host=HOST, requeues=1)
    assert again is not None and again.attempts == 2
    assert store.set_progress(job.id, 50, "old", attempt=1) is None
    assert store.set_progress(job.id, 50, "new", attempt=2) is JobStatus.running
    assert store.get_job(job.id).message == "new"
    assert store.transition(job.id, JobStatus.running, requeues=0) is None


def test_a_tiled_job_is_left_to_its_tiles_until_the_broker_would_have_given_them_back(
    settings: Settings, store: Store
) -> None:
    """No process holds a job while its tiles run (its splitting process may be gone): the
    tiles beat for it, and a sweep takes it back only once nothing beat for longer than the
    broker's visibility timeout (every message of its tiles lost)."""
    job = running_job(store, pid=gone_pid())
    assert store.hand_to_tiles(job.id, job.attempts)
    assert not store.hand_to_tiles(job.id, job.attempts + 1)  # another delivery's: refused
    queue = Queue()
    quiet = settings.visibility_timeout  # far beyond STALE_JOB_SECONDS
    assert janitor(settings, store, queue).sweep(now=later(quiet)) == []
    assert store.beat([job.id], TILED_HOST) == 1  # a tile task or its worker
    beaten = store.get_job(job.id)
    assert beaten is not None and (beaten.worker_host, beaten.worker_pid) == (TILED_HOST, None)
    assert janitor(settings, store, queue).sweep(now=later(quiet)) == []
    [taken] = janitor(settings, store, queue).sweep(
        now=later(settings.visibility_timeout + settings.stale_job_seconds + 5))
    assert (taken.status, taken.requeues) == (JobStatus.accepted, 1)
    assert "tiles sent no heartbeat" in taken.message and queue.sent == [(job.id, 1)]
