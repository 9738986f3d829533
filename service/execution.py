"""How an execute request wants to be answered (RFC 7240 ``Prefer``) and who it wants told
(``subscriber``), free of FastAPI.

Execution is asynchronous by default: 201, ``Location`` and the status document. ``Prefer:
respond-async`` asks for that explicitly and is acknowledged in ``Preference-Applied``.
``Prefer: wait`` (optionally ``wait=<seconds>``) asks for synchronous execution: for a cloud of
at most SYNC_MAX_POINTS points the API waits for the job (at most SYNC_WAIT_SECONDS, or the
given seconds when fewer) and answers 200 with the results document; a larger cloud, or a job
still running at the deadline, is answered asynchronously without ``Preference-Applied``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

from lidar_outliers.jobs.callbacks import CallbackRefused, parse_subscriber
from lidar_outliers.jobs.settings import Settings
from lidar_outliers.jobs.store import FINAL, Job, Store
from service.problems import Problem

POLL_SECONDS = 0.2


@dataclass
class Preference:
    respond_async: bool = False
    wait: bool = False
    #: seconds of ``wait=N``; None when not given
    wait_seconds: float | None = None

    @classmethod
    def parse(cls, headers: list[str]) -> Preference:
        """The preferences of every ``Prefer`` header (comma-separated tokens, parameters after
        ``;`` ignored); unknown ones are ignored, as RFC 7240 asks."""
        found = cls()
        for header in headers:
            for token in header.split(","):
                name, _, value = token.split(";")[0].strip().partition("=")
                name = name.strip().lower()
                if name == "respond-async":
                    found.respond_async = True
                elif name == "wait":
                    found.wait = True
                    try:
                        found.wait_seconds = max(0.0, float(value.strip().strip('"')))
                    except ValueError:
                        found.wait_seconds = None
        return found

    def synchronous(self, job: Job, settings: Settings) -> bool:
        """Whether to wait for this job: asked for, not contradicted, and small enough."""
        points = int(job.facts.get("points", 0) or 0)
        return self.wait and not self.respond_async and points <= settings.sync_max_points

    def deadline(self, settings: Settings) -> float:
        limit = settings.sync_wait_seconds
        if self.wait_seconds is not None:
            limit = min(limit, self.wait_seconds)
        return time.monotonic() + limit

    def applied(self) -> str:
        if self.wait_seconds is not None:
            return f"wait={self.wait_seconds:g}"
        return "wait"


def wait_for(store: Store, job: Job, deadline: float) -> Job:
    """The job once final, or as it is at the deadline."""
    while True:
        current = store.get_job(job.id) or job
        if current.status in FINAL or time.monotonic() >= deadline:
            return current
        time.sleep(POLL_SECONDS)


def subscriber_of(value: Any, settings: Settings, base_url: str) -> dict[str, str] | None:
    """The request's ``subscriber`` checked by the callback guard, with the API's base URL;
    None without one. Raises Problem 422 naming the refused key."""
    if value is None:
        return None
    try:
        uris = parse_subscriber(value, settings.callback_allow_list)
    except CallbackRefused as exc:
        parameter = str(exc).split(":", 1)[0]
        raise Problem(422, "invalid-parameter", str(exc),
                      errors=[{"parameter": parameter, "message": str(exc)}]) from None
    return {**uris, "base_url": base_url.rstrip("/")} if uris else None
