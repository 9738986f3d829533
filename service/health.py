"""The state of the service's parts for ``/health``, checked in the background and cached.

A worker ping waits its whole timeout for replies, so checking on every request would make
``/health`` slow and would send a control message per request to every worker. Instead the
parts are checked every ``HEALTH_INTERVAL_SECONDS`` by the API's background task, and on
request when the last check is older than twice that or found something down (so a recovery
shows at once; concurrent requests then share one check).

Two reports come out of one check: the public one (component states only: no host names, URLs
or exception text) for callers without a key, and the detailed one for callers with a key.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from typing import Any

import redis

from lidar_outliers.jobs.settings import Settings
from lidar_outliers.jobs.storage import Storage, StorageError
from lidar_outliers.jobs.store import Store
from service import queue


@dataclass
class Report:
    """One check of the service's parts."""

    checked: float
    #: component -> "ok" or "unreachable"
    states: dict[str, str] = field(default_factory=dict)
    workers: list[str] = field(default_factory=list)
    #: What is wrong, for anyone (names the part, nothing about where it runs).
    public_detail: str = ""
    #: What is wrong with addresses and errors, for callers with a key.
    detail: str = ""

    @property
    def ok(self) -> bool:
        return not self.public_detail

    def body(self, detailed: bool) -> dict[str, Any]:
        body: dict[str, Any] = {"api": "ok", **self.states}
        body["workers"] = self.workers if detailed else len(self.workers)
        return body


def _redis_address(url: str) -> str:
    """The Redis URL without its password."""
    scheme, sep, rest = url.partition("://")
    return f"{scheme}{sep}{rest.rsplit('@', 1)[-1]}"


def check(settings: Settings, store: Store, storage: Storage) -> Report:
    """Check the database, the storage, Redis and the workers, in this order, stopping at the
    first part that does not answer."""
    report = Report(checked=time.monotonic())
    try:
        store.count_active(0)
        report.states["database"] = "ok"
    except Exception as exc:  # any failure of the database is the answer
        report.states["database"] = "unreachable"
        report.public_detail = "the database is not reachable"
        report.detail = f"the database {store.describe()} is not reachable: {exc}"
        return report
    try:
        storage.check()
        report.states["storage"] = "ok"
    except StorageError as exc:
        report.states["storage"] = "unreachable"
        report.public_detail = "the file storage is not usable"
        report.detail = str(exc)
        return report
    try:
        redis.Redis.from_url(settings.redis_url, socket_timeout=2.0,
                             socket_connect_timeout=2.0).ping()
        report.states["redis"] = "ok"
    except Exception as exc:  # any connection failure is the answer
        report.states["redis"] = "unreachable"
        report.public_detail = "the job queue (Redis) is not reachable"
        report.detail = (f"Redis at {_redis_address(settings.redis_url)} is not reachable: "
                         f"{exc}")
        return report
    try:
        report.workers = queue.ping_workers(settings)
    except Exception as exc:  # a broken connection is "no worker answered" too
        report.detail = f"pinging the workers failed: {exc}"
    if not report.workers:
        report.public_detail = ("no Celery worker answered; start one with `celery -A "
                                "worker.celery_app worker` (or `make run`)")
        report.detail = report.detail or report.public_detail
    return report


class HealthMonitor:
    """The last report, refreshed at most every ``settings.health_interval_seconds``."""

    def __init__(self, settings: Settings, store: Store, storage: Storage) -> None:
        self.settings = settings
        self.store = store
        self.storage = storage
        self._last: Report | None = None
        self._lock = threading.Lock()

    @property
    def interval(self) -> float:
        return self.settings.health_interval_seconds

    def refresh(self) -> Report:
        """Check now (one check at a time: callers arriving meanwhile share its result)."""
        started = time.monotonic()
        with self._lock:
            if self._last is not None and self._last.checked >= started:
                return self._last  # checked by another caller while this one waited
            report = check(self.settings, self.store, self.storage)
            report.checked = time.monotonic()  # its result is news to whoever came meanwhile
            self._last = report
            return report

    def report(self) -> Report:
        """The cached report when it is recent and good; a new check otherwise."""
        last = self._last
        if last is not None and last.ok and time.monotonic() - last.checked < 2 * self.interval:
            return last
        return self.refresh()
