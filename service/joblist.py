"""The filters of GET /jobs (OGC API - Processes, job-list class), free of FastAPI: ``type``
(every job here is of type ``process``), ``processID``, ``status``, ``datetime`` (an instant or
an interval of ``created``), ``minDuration`` / ``maxDuration`` (seconds from ``started`` to
``finished``, or to now for a running job; a job not started yet has no duration and is left
out when they are given).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from datetime import UTC, datetime

from lidar_outliers.jobs.store import Job, JobStatus, Store, parse_time
from service.problems import Problem

OPEN = ("", "..")


def _bad(parameter: str, message: str) -> Problem:
    return Problem(400, "invalid-parameter", f"{parameter}: {message}",
                   errors=[{"parameter": parameter, "in": "query", "message": message}])


def split_values(values: list[str]) -> list[str]:
    """Repeated parameters and comma-separated lists alike (``status=a&status=b`` or
    ``status=a,b``)."""
    return [v.strip() for value in values for v in value.split(",") if v.strip()]


def _stamp(text: str) -> str:
    """An RFC 3339 date-time as the store writes times (UTC, milliseconds, Z)."""
    # an unencoded '+' of an offset arrives as a space
    text = text.strip().replace(" ", "+")
    try:
        moment = datetime.fromisoformat(text.replace("z", "Z").replace("Z", "+00:00"))
    except ValueError:
        raise _bad("datetime", f"{text!r} is not an RFC 3339 date-time") from None
    if moment.tzinfo is None:
        raise _bad("datetime", f"{text!r} has no time zone (add Z or an offset)")
    try:
        utc = moment.astimezone(UTC)
    except OverflowError:  # year 1 east of UTC, year 9999 west of it
        raise _bad("datetime", f"{text!r} lies outside the years 1-9999 in UTC") from None
    return utc.isoformat(timespec="milliseconds").replace("+00:00", "Z")


def parse_datetime(value: str | None) -> tuple[str | None, str | None]:
    """``datetime`` as the inclusive bounds of ``created`` (None: open; an empty value is no
    filter, as an absent one)."""
    if not value:
        return None, None
    if "/" not in value:
        stamp = _stamp(value)
        return stamp, stamp
    start, _, end = value.partition("/")
    if "/" in end:
        raise _bad("datetime", "an interval has one '/'")
    low = None if start.strip() in OPEN else _stamp(start)
    high = None if end.strip() in OPEN else _stamp(end)
    if low is None and high is None:
        raise _bad("datetime", "'../..' bounds nothing; give a start or an end")
    if low and high and low > high:
        raise _bad("datetime", "the interval ends before it starts")
    return low, high


def duration(job: Job, now: datetime) -> float | None:
    """Seconds the job ran (so far, when running); None when it never started."""
    if job.started is None:
        return None
    end = parse_time(job.finished) if job.finished else now
    return (end - parse_time(job.started)).total_seconds()


@dataclass
class JobFilter:
    process_ids: list[str] = field(default_factory=list)
    statuses: list[str] = field(default_factory=list)
    datetime: str | None = None
    min_duration: int | None = None
    max_duration: int | None = None
    types: list[str] = field(default_factory=list)

    def check(self) -> None:
        known = {s.value for s in JobStatus}
        for status in self.statuses:
            if status not in known:
                raise _bad("status", f"{status!r} is not one of {', '.join(sorted(known))}")
        for name, limit in (("minDuration", self.min_duration),
                            ("maxDuration", self.max_duration)):
            if limit is not None and limit < 0:
                raise _bad(name, "must be a number of seconds >= 0")
        if (self.min_duration is not None and self.max_duration is not None
                and self.min_duration > self.max_duration):
            raise _bad("minDuration", "exceeds maxDuration")

    def select(self, store: Store, user_id: int, limit: int,
               offset: int) -> tuple[list[Job], int]:
        """One page of the user's matching jobs, newest first, and how many match in all."""
        self.check()
        if self.types and "process" not in self.types:
            return [], 0
        low, high = parse_datetime(self.datetime)
        jobs = store.find_jobs(user_id, self.process_ids or None, self.statuses or None,
                               low, high)
        if self.min_duration is not None or self.max_duration is not None:
            now = datetime.now(UTC)
            lower = self.min_duration if self.min_duration is not None else 0
            upper = self.max_duration if self.max_duration is not None else float("inf")
            jobs = [j for j in jobs
                    if (d := duration(j, now)) is not None and lower <= d <= upper]
        return jobs[offset:offset + limit], len(jobs)
