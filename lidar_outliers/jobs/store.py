"""Job records, uploads and API keys in SQLite (the default, a file under ``DATA_DIR``) or
PostgreSQL (``DATABASE_URL``), through SQLAlchemy Core.

The API and the worker processes, on one host or several, share the database; every operation
is one short transaction. Keys are stored only as sha256 hashes. The schema is the one of
:mod:`lidar_outliers.jobs.schema`, brought up to date when a store is opened
(:func:`lidar_outliers.jobs.database.upgrade`).

:meth:`Store.transition` is the one place that moves a job between states
(accepted -> running -> successful / failed / dismissed) and records failures;
:meth:`Store.reclaim` alone moves a job of a vanished worker (running -> accepted or failed).

Limits hold under concurrency: :meth:`Store.create_job` and :meth:`Store.add_upload` check the
user's active jobs and stored bytes and insert the record in one transaction that first locks
the user (``SELECT ... FOR UPDATE`` on PostgreSQL; SQLite's write lock, taken at ``BEGIN
IMMEDIATE``), so two requests of one user cannot both pass a check that only one may pass.
"""

from __future__ import annotations

import hashlib
import json
import secrets
import uuid
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import UTC, datetime
from enum import StrEnum
from pathlib import Path
from typing import Any

import sqlalchemy as sa

from lidar_outliers.errors import LidarOutliersError
from lidar_outliers.jobs import database
from lidar_outliers.jobs.schema import jobs, resumable_uploads, uploads, users


class StoreError(LidarOutliersError):
    """A user or job operation that cannot be done (unknown user, name taken, ...)."""


class LimitExceeded(StoreError):
    """A new job or upload would take the user over a limit; nothing was recorded."""


class TooManyActiveJobs(LimitExceeded):
    def __init__(self, active: int, limit: int) -> None:
        super().__init__(f"{active} queued or running jobs, the limit is {limit}")
        self.active = active
        self.limit = limit


class QuotaExceeded(LimitExceeded):
    def __init__(self, stored: int, requested: int, limit: int) -> None:
        super().__init__(f"{stored} bytes stored + {requested} new would exceed the quota of "
                         f"{limit} bytes")
        self.stored = stored
        self.requested = requested
        self.limit = limit

    @property
    def left(self) -> int:
        return max(0, self.limit - self.stored)


class JobStatus(StrEnum):
    """OGC API - Processes status codes."""

    accepted = "accepted"
    running = "running"
    successful = "successful"
    failed = "failed"
    dismissed = "dismissed"


ACTIVE = (JobStatus.accepted, JobStatus.running)
FINAL = (JobStatus.successful, JobStatus.failed, JobStatus.dismissed)

#: Allowed moves; anything else is refused (e.g. a late worker cannot resurrect a dismissed job).
TRANSITIONS: dict[JobStatus, set[JobStatus]] = {
    JobStatus.accepted: {JobStatus.running, JobStatus.failed, JobStatus.dismissed},
    # running -> running: a job re-delivered after its worker died starts again;
    # running -> accepted: its worker vanished and the job was put back in the queue.
    JobStatus.running: {
        JobStatus.accepted,
        JobStatus.running,
        JobStatus.successful,
        JobStatus.failed,
        JobStatus.dismissed,
    },
    JobStatus.successful: {JobStatus.dismissed},
    JobStatus.failed: {JobStatus.dismissed},
    JobStatus.dismissed: set(),
}


#: The ``worker_host`` of a running job whose tiles run on the workers (no one process holds
#: it); the tile tasks beat for it with this host (:meth:`Store.beat`).
TILED_HOST = "(tiles)"


def now() -> str:
    """UTC time as ISO 8601 with a Z, as OGC API - Processes writes it."""
    return datetime.now(UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")


def parse_time(text: str) -> datetime:
    return datetime.fromisoformat(text.replace("Z", "+00:00"))


def hash_key(key: str) -> str:
    return hashlib.sha256(key.encode()).hexdigest()


@dataclass
class User:
    id: int
    name: str
    created: str
    revoked: str | None = None


@dataclass
class Upload:
    id: str
    user_id: int
    name: str
    #: Where the file is in the object storage (:mod:`lidar_outliers.jobs.storage`).
    key: str
    bytes: int
    created: str
    #: Header facts of a cloud, or the summary of a trajectory (None for older uploads).
    facts: dict[str, Any] | None = None

    @classmethod
    def from_row(cls, row: Mapping[str, Any]) -> Upload:
        facts = row["facts"]
        return cls(id=row["id"], user_id=row["user_id"], name=row["name"], key=row["key"],
                   bytes=int(row["bytes"]), created=row["created"],
                   facts=json.loads(facts) if facts else None)


@dataclass
class Resumable:
    """An upload still arriving in pieces (tus); its bytes so far lie on ``host``'s disk."""

    id: str
    user_id: int
    name: str
    kind: str
    length: int
    offset: int
    created: str
    expires: str
    host: str

    @classmethod
    def from_row(cls, row: Mapping[str, Any]) -> Resumable:
        return cls(id=row["id"], user_id=row["user_id"], name=row["name"], kind=row["kind"],
                   length=int(row["length"]), offset=int(row["offset"]),
                   created=row["created"], expires=row["expires"], host=row["host"])


@dataclass
class Job:
    id: str
    user_id: int
    process_id: str
    status: JobStatus
    progress: int
    message: str
    created: str
    started: str | None
    finished: str | None
    inputs: dict[str, Any]
    facts: dict[str, Any]
    laz: bool
    attempts: int = 0
    worker_pid: int | None = None
    stored_bytes: int = 0
    #: When the worker running the job last said it is alive, and that worker's host.
    heartbeat: str | None = None
    worker_host: str | None = None
    #: Times the job was put back in the queue after its worker vanished.
    requeues: int = 0
    #: The user's n-th job (lists are in this order).
    seq: int = 0
    #: Callback URIs (successUri, failedUri, inProgressUri) and the API's base_url, or None.
    subscriber: dict[str, str] | None = None
    #: Set by :meth:`Store.create_job` only: the user's active jobs before this one (its queue
    #: priority); not stored.
    active_before: int = 0

    @classmethod
    def from_row(cls, row: Mapping[str, Any]) -> Job:
        return cls(
            id=row["id"],
            user_id=row["user_id"],
            process_id=row["process_id"],
            status=JobStatus(row["status"]),
            progress=row["progress"],
            message=row["message"],
            created=row["created"],
            started=row["started"],
            finished=row["finished"],
            inputs=json.loads(row["inputs"]),
            facts=json.loads(row["facts"]),
            laz=bool(row["laz"]),
            attempts=row["attempts"],
            worker_pid=row["worker_pid"],
            stored_bytes=int(row["stored_bytes"]),
            seq=row["seq"],
            subscriber=json.loads(row["subscriber"]) if row["subscriber"] else None,
            heartbeat=row["heartbeat"],
            worker_host=row["worker_host"],
            requeues=row["requeues"],
        )


def _user(row: Mapping[str, Any]) -> User:
    return User(id=row["id"], name=row["name"], created=row["created"], revoked=row["revoked"])


#: Statements of every request, built once (building one costs more than running it).
_USER_FOR_KEY = sa.select(users).where(users.c.key_hash == sa.bindparam("key_hash"),
                                       users.c.revoked.is_(None))
_JOB = sa.select(jobs).where(jobs.c.id == sa.bindparam("job_id"))
#: A user by key hash and, joined when it is theirs, one job (built once: polls are frequent).
_JOB_FOR_KEY = (
    sa.select(users, *[c.label(f"job_{c.name}") for c in jobs.c])
    .select_from(users.outerjoin(jobs, sa.and_(jobs.c.user_id == users.c.id,
                                               jobs.c.id == sa.bindparam("job_id"))))
    .where(users.c.key_hash == sa.bindparam("key_hash"), users.c.revoked.is_(None))
)


class Store:
    """Users, uploads and jobs in one database. Opening one migrates the schema (unless
    ``migrate`` is False: the caller knows it is current); share one per process."""

    def __init__(self, url: str | Path, *, migrate: bool = True) -> None:
        self.url = database.normalise_url(url)
        self.engine = database.create_engine(url)
        if migrate:
            database.upgrade(self.engine)

    @property
    def path(self) -> Path | None:
        """The SQLite file, or None for another database."""
        return database.sqlite_file(self.url)

    def describe(self) -> str:
        """Where the records are, for messages (no password)."""
        return self.url.render_as_string(hide_password=True)

    def close(self) -> None:
        """Close the pooled connections (before a fork, or when done)."""
        self.engine.dispose()

    @contextmanager
    def _read(self) -> Iterator[sa.Connection]:
        with self.engine.connect() as db:
            yield db

    @contextmanager
    def _transaction(self) -> Iterator[sa.Connection]:
        """A writing transaction: committed at the end of the block, rolled back on error."""
        with self.engine.connect() as db:
            db.execution_options(**{database.WRITE: True})
            with db.begin():
                yield db

    @staticmethod
    def _lock_user(db: sa.Connection, user_id: int) -> None:
        """Serialise the user's reservations until the transaction ends."""
        row = db.execute(
            sa.select(users.c.id).where(users.c.id == user_id).with_for_update()
        ).first()
        if row is None:
            raise StoreError(f"no user with id {user_id}")

    @staticmethod
    def _stored_bytes(db: sa.Connection, user_id: int) -> int:
        in_jobs = db.execute(
            sa.select(sa.func.coalesce(sa.func.sum(jobs.c.stored_bytes), 0))
            .where(jobs.c.user_id == user_id)
        ).scalar_one()
        in_uploads = db.execute(
            sa.select(sa.func.coalesce(sa.func.sum(uploads.c.bytes), 0))
            .where(uploads.c.user_id == user_id)
        ).scalar_one()
        # an unfinished resumable upload holds its announced length
        arriving = db.execute(
            sa.select(sa.func.coalesce(sa.func.sum(resumable_uploads.c.length), 0))
            .where(resumable_uploads.c.user_id == user_id)
        ).scalar_one()
        return int(in_jobs) + int(in_uploads) + int(arriving)

    @staticmethod
    def _count_active(db: sa.Connection, user_id: int) -> int:
        return int(db.execute(
            sa.select(sa.func.count()).select_from(jobs)
            .where(jobs.c.user_id == user_id, jobs.c.status.in_([s.value for s in ACTIVE]))
        ).scalar_one())

    def _check_quota(self, db: sa.Connection, user_id: int, size: int,
                     limit: int | None) -> None:
        if limit is None:
            return
        stored = self._stored_bytes(db, user_id)
        if stored + size > limit:
            raise QuotaExceeded(stored, size, limit)

    # ---- users -------------------------------------------------------------------------------

    def add_user(self, name: str) -> tuple[User, str]:
        """Create a user and return it with its new key (the only time the key is visible)."""
        name = name.strip()
        if not name or len(name) > 100 or any(c.isspace() for c in name):
            raise StoreError(f"user name must be 1-100 characters without spaces, got {name!r}")
        key = "lo_" + secrets.token_urlsafe(32)
        created = now()
        taken = StoreError(f"user {name!r} exists; revoke it first or choose another name")
        try:
            with self._transaction() as db:
                if db.execute(sa.select(users.c.id).where(users.c.name == name)).first():
                    raise taken
                user_id = db.execute(
                    sa.insert(users).values(name=name, key_hash=hash_key(key), created=created)
                    .returning(users.c.id)
                ).scalar_one()
        except sa.exc.IntegrityError:  # added by another process since the check
            raise taken from None
        return User(id=user_id, name=name, created=created), key

    def list_users(self) -> list[User]:
        with self._read() as db:
            rows = db.execute(sa.select(users).order_by(users.c.id)).mappings().all()
        return [_user(r) for r in rows]

    def revoke_user(self, name: str) -> None:
        """Invalidate a user's key. The name is freed (a new key can be issued under it) by
        renaming the revoked row; its jobs stay until retention deletes them."""
        with self._transaction() as db:
            user_id = db.execute(
                sa.select(users.c.id).where(users.c.name == name, users.c.revoked.is_(None))
                .with_for_update()
            ).scalar()
            if user_id is None:
                raise StoreError(f"no active user named {name!r}")
            db.execute(
                sa.update(users).where(users.c.id == user_id).values(
                    revoked=now(), name=f"{name}#revoked-{user_id}",
                    key_hash="revoked-" + secrets.token_hex(16),
                )
            )

    def user_for_key(self, key: str) -> User | None:
        with self._read() as db:
            row = db.execute(_USER_FOR_KEY, {"key_hash": hash_key(key)}).mappings().first()
        return _user(row) if row else None

    def job_for_key(self, key: str, job_id: str) -> tuple[User | None, Job | None]:
        """The key's user and that user's job ``job_id``, in one query (a status poll's whole
        database work): (None, None) for a wrong or revoked key, (user, None) when the job is
        not the user's or does not exist."""
        with self._read() as db:
            row = db.execute(_JOB_FOR_KEY, {"key_hash": hash_key(key), "job_id": job_id}
                             ).mappings().first()
        if row is None:
            return None, None
        if row["job_id"] is None:
            return _user(row), None
        return _user(row), Job.from_row({c.name: row[f"job_{c.name}"] for c in jobs.c})

    # ---- uploads -----------------------------------------------------------------------------

    def add_upload(
        self, user_id: int, name: str, key: str, size: int,
        facts: dict[str, Any] | None = None, *, max_stored_bytes: int | None = None,
        upload_id: str | None = None,
    ) -> Upload:
        """Record an upload; with ``max_stored_bytes``, refuse it (:class:`QuotaExceeded`) when
        the user's stored bytes plus ``size`` would exceed that, checked in the same
        transaction."""
        upload = Upload(id=upload_id or uuid.uuid4().hex, user_id=user_id, name=name, key=key,
                        bytes=size, created=now(), facts=facts)
        with self._transaction() as db:
            self._lock_user(db, user_id)
            self._check_quota(db, user_id, size, max_stored_bytes)
            db.execute(sa.insert(uploads).values(
                id=upload.id, user_id=user_id, name=name, key=key, bytes=size,
                created=upload.created, facts=json.dumps(facts) if facts is not None else None,
            ))
        return upload

    def get_upload(self, upload_id: str, user_id: int) -> Upload | None:
        with self._read() as db:
            row = db.execute(
                sa.select(uploads).where(uploads.c.id == upload_id, uploads.c.user_id == user_id)
            ).mappings().first()
        return Upload.from_row(row) if row else None

    def delete_upload(self, upload_id: str) -> None:
        with self._transaction() as db:
            db.execute(sa.delete(uploads).where(uploads.c.id == upload_id))

    def uploads_created_before(self, stamp: str) -> list[Upload]:
        with self._read() as db:
            rows = db.execute(
                sa.select(uploads).where(uploads.c.created < stamp)
            ).mappings().all()
        return [Upload.from_row(r) for r in rows]

    # ---- resumable uploads -------------------------------------------------------------------

    def add_resumable(
        self, user_id: int, name: str, kind: str, length: int, expires: str, host: str, *,
        max_stored_bytes: int | None = None,
    ) -> Resumable:
        """Record a new resumable upload of ``length`` bytes, reserved against the user's quota
        in the same transaction (:class:`QuotaExceeded` when it does not fit)."""
        upload = Resumable(id=uuid.uuid4().hex, user_id=user_id, name=name, kind=kind,
                           length=length, offset=0, created=now(), expires=expires, host=host)
        with self._transaction() as db:
            self._lock_user(db, user_id)
            self._check_quota(db, user_id, length, max_stored_bytes)
            db.execute(sa.insert(resumable_uploads).values(
                id=upload.id, user_id=user_id, name=name, kind=kind, length=length, offset=0,
                created=upload.created, expires=expires, host=host))
        return upload

    def get_resumable(self, upload_id: str, user_id: int) -> Resumable | None:
        with self._read() as db:
            row = db.execute(
                sa.select(resumable_uploads).where(resumable_uploads.c.id == upload_id,
                                                   resumable_uploads.c.user_id == user_id)
            ).mappings().first()
        return Resumable.from_row(row) if row else None

    def set_resumable_offset(self, upload_id: str, offset: int, expires: str) -> None:
        with self._transaction() as db:
            db.execute(sa.update(resumable_uploads).where(resumable_uploads.c.id == upload_id)
                       .values(offset=offset, expires=expires))

    def complete_resumable(self, upload: Resumable, key: str,
                           facts: dict[str, Any] | None) -> Upload:
        """The arrived upload becomes an ordinary one under the same id, in one transaction:
        its reserved bytes pass from one table to the other, so the quota never counts them
        twice nor drops them."""
        done = Upload(id=upload.id, user_id=upload.user_id, name=upload.name, key=key,
                      bytes=upload.length, created=now(), facts=facts)
        with self._transaction() as db:
            removed = db.execute(sa.delete(resumable_uploads)
                                 .where(resumable_uploads.c.id == upload.id)).rowcount
            if not removed:
                raise StoreError(f"no resumable upload {upload.id!r}")
            db.execute(sa.insert(uploads).values(
                id=done.id, user_id=done.user_id, name=done.name, key=key, bytes=done.bytes,
                created=done.created, facts=json.dumps(facts) if facts is not None else None))
        return done

    def delete_resumable(self, upload_id: str) -> bool:
        with self._transaction() as db:
            return bool(db.execute(sa.delete(resumable_uploads)
                                   .where(resumable_uploads.c.id == upload_id)).rowcount)

    def resumables_expired(self, stamp: str, user_id: int | None = None) -> list[Resumable]:
        """Unfinished uploads whose expiry is before ``stamp`` (of one user when given)."""
        query = sa.select(resumable_uploads).where(resumable_uploads.c.expires < stamp)
        if user_id is not None:
            query = query.where(resumable_uploads.c.user_id == user_id)
        with self._read() as db:
            rows = db.execute(query).mappings().all()
        return [Resumable.from_row(r) for r in rows]

    # ---- jobs --------------------------------------------------------------------------------

    def create_job(
        self,
        user_id: int,
        process_id: str,
        inputs: dict[str, Any],
        facts: dict[str, Any],
        laz: bool,
        stored_bytes: int,
        job_id: str | None = None,
        *,
        max_active: int | None = None,
        max_stored_bytes: int | None = None,
        subscriber: dict[str, str] | None = None,
    ) -> Job:
        """Record a new accepted job that holds ``stored_bytes``.

        With ``max_active``, refuse it (:class:`TooManyActiveJobs`) when the user already has
        that many queued or running jobs; with ``max_stored_bytes``, refuse it
        (:class:`QuotaExceeded`) when its bytes do not fit the user's quota. The checks and the
        insert are one transaction under the user's lock: concurrent submissions never take a
        user over either limit.
        """
        job = Job(
            id=job_id or uuid.uuid4().hex,
            user_id=user_id,
            process_id=process_id,
            status=JobStatus.accepted,
            progress=0,
            message="queued",
            created=now(),
            started=None,
            finished=None,
            inputs=inputs,
            facts=facts,
            laz=laz,
            stored_bytes=stored_bytes,
            subscriber=subscriber,
        )
        with self._transaction() as db:
            self._lock_user(db, user_id)
            active = self._count_active(db, user_id)
            if max_active is not None and active >= max_active:
                raise TooManyActiveJobs(active, max_active)
            self._check_quota(db, user_id, stored_bytes, max_stored_bytes)
            job.seq = int(db.execute(
                sa.select(sa.func.coalesce(sa.func.max(jobs.c.seq), 0) + 1)
                .where(jobs.c.user_id == user_id)
            ).scalar_one())
            db.execute(sa.insert(jobs).values(
                id=job.id, user_id=user_id, process_id=process_id, status=job.status.value,
                progress=0, message=job.message, created=job.created, inputs=json.dumps(inputs),
                facts=json.dumps(facts), laz=int(laz), stored_bytes=stored_bytes, seq=job.seq,
                subscriber=json.dumps(subscriber) if subscriber else None,
            ))
        job.active_before = active
        return job

    def get_job(self, job_id: str) -> Job | None:
        with self._read() as db:
            row = db.execute(_JOB, {"job_id": job_id}).mappings().first()
        return Job.from_row(row) if row else None

    def list_jobs(self, user_id: int, limit: int, offset: int) -> tuple[list[Job], int]:
        """The user's jobs, newest first, and how many there are in all."""
        with self._read() as db:
            rows = db.execute(
                sa.select(jobs).where(jobs.c.user_id == user_id)
                .order_by(jobs.c.seq.desc()).limit(limit).offset(offset)
            ).mappings().all()
            total = db.execute(
                sa.select(sa.func.count()).select_from(jobs).where(jobs.c.user_id == user_id)
            ).scalar_one()
        return [Job.from_row(r) for r in rows], int(total)

    def find_jobs(self, user_id: int, process_ids: list[str] | None = None,
                  statuses: list[str] | None = None, created_from: str | None = None,
                  created_to: str | None = None) -> list[Job]:
        """The user's jobs matching every given filter, newest first (``created_*``: ISO 8601
        UTC with a Z as stored, bounds included)."""
        query = sa.select(jobs).where(jobs.c.user_id == user_id)
        if process_ids:
            query = query.where(jobs.c.process_id.in_(process_ids))
        if statuses:
            query = query.where(jobs.c.status.in_(statuses))
        if created_from:
            query = query.where(jobs.c.created >= created_from)
        if created_to:
            query = query.where(jobs.c.created <= created_to)
        with self._read() as db:
            rows = db.execute(query.order_by(jobs.c.seq.desc())).mappings().all()
        return [Job.from_row(r) for r in rows]

    def count_active(self, user_id: int) -> int:
        with self._read() as db:
            return self._count_active(db, user_id)

    def stored_bytes(self, user_id: int) -> int:
        """Bytes the user keeps on the server: jobs' files and uploads."""
        with self._read() as db:
            return self._stored_bytes(db, user_id)

    def jobs_finished_before(self, stamp: str) -> list[Job]:
        with self._read() as db:
            rows = db.execute(
                sa.select(jobs).where(jobs.c.finished.is_not(None), jobs.c.finished < stamp)
            ).mappings().all()
        return [Job.from_row(r) for r in rows]

    def delete_job(self, job_id: str) -> None:
        with self._transaction() as db:
            db.execute(sa.delete(jobs).where(jobs.c.id == job_id))

    def transition(
        self,
        job_id: str,
        status: JobStatus,
        message: str | None = None,
        *,
        worker_pid: int | None = None,
        worker_host: str | None = None,
        stored_bytes: int | None = None,
        requeues: int | None = None,
    ) -> Job | None:
        """Move a job to ``status`` if the move is allowed; return the job as stored afterwards,
        or None when the move is refused (unknown job, already final such as dismissed, or,
        with ``requeues``, re-queued since the delivery asking was sent)."""
        with self._transaction() as db:
            row = db.execute(
                sa.select(jobs.c.status, jobs.c.attempts, jobs.c.requeues)
                .where(jobs.c.id == job_id).with_for_update()
            ).mappings().first()
            if row is None:
                return None
            current = JobStatus(row["status"])
            if status not in TRANSITIONS[current]:
                return None
            if requeues is not None and row["requeues"] != requeues:
                return None
            sets: dict[str, Any] = {"status": status.value}
            if message is not None:
                sets["message"] = message
            stamp = now()
            if status is JobStatus.running:
                sets["started"] = stamp
                sets["attempts"] = row["attempts"] + 1
                sets["worker_pid"] = worker_pid
                sets["worker_host"] = worker_host
                sets["heartbeat"] = stamp
                sets["progress"] = 0
            elif status in FINAL:
                sets["finished"] = stamp
                sets["worker_pid"] = None
            if status is JobStatus.successful:
                sets["progress"] = 100
            if stored_bytes is not None:
                sets["stored_bytes"] = stored_bytes
            db.execute(sa.update(jobs).where(jobs.c.id == job_id).values(**sets))
            updated = db.execute(sa.select(jobs).where(jobs.c.id == job_id)).mappings().one()
        return Job.from_row(updated)

    def set_progress(self, job_id: str, percent: int, message: str,
                     attempt: int | None = None) -> JobStatus | None:
        """Record progress of a running job; return its status (the worker stops on dismissed).

        With ``attempt`` (the delivery's number, :attr:`Job.attempts` when it started), only
        that delivery may report: for an older one, whose job was re-queued or started again
        elsewhere, nothing is written and the answer is None, as for an unknown job."""
        where = [jobs.c.id == job_id, jobs.c.status == JobStatus.running.value]
        if attempt is not None:
            where.append(jobs.c.attempts == attempt)
        with self._transaction() as db:
            changed = db.execute(
                sa.update(jobs).where(*where)
                .values(progress=max(0, min(99, percent)), message=message)
            ).rowcount
            if changed:
                return JobStatus.running
            row = db.execute(sa.select(jobs.c.status, jobs.c.attempts)
                             .where(jobs.c.id == job_id)).first()
        if row is None or (attempt is not None and row.attempts != attempt):
            return None
        return JobStatus(row.status)

    def beat(self, job_ids: list[str], host: str) -> int:
        """Heartbeat of the jobs a worker on ``host`` runs; returns how many were running."""
        if not job_ids:
            return 0
        with self._transaction() as db:
            return db.execute(
                sa.update(jobs).where(jobs.c.id.in_(job_ids),
                                      jobs.c.status == JobStatus.running.value,
                                      jobs.c.worker_host == host)
                .values(heartbeat=now())
            ).rowcount

    def hand_to_tiles(self, job_id: str, attempt: int) -> bool:
        """Record that delivery ``attempt`` of a running job handed its tiles to the queue: no
        one process holds the job now (``worker_host`` :data:`TILED_HOST`, no ``worker_pid``);
        its tile tasks keep its heartbeat. False when the job is no longer that delivery's."""
        with self._transaction() as db:
            return bool(db.execute(
                sa.update(jobs).where(jobs.c.id == job_id,
                                      jobs.c.status == JobStatus.running.value,
                                      jobs.c.attempts == attempt)
                .values(worker_pid=None, worker_host=TILED_HOST, heartbeat=now())
            ).rowcount)

    def running_jobs(self) -> list[Job]:
        with self._read() as db:
            rows = db.execute(
                sa.select(jobs).where(jobs.c.status == JobStatus.running.value)
            ).mappings().all()
        return [Job.from_row(r) for r in rows]

    def reclaim(self, job: Job, message: str, *, give_up: bool = False,
                stored_bytes: int | None = None) -> Job | None:
        """Take back a running job whose worker vanished, as ``job`` was read: put it back in
        the queue (accepted, one more re-queue) or, with ``give_up``, fail it with ``message``.

        Nothing happens (None) when the job changed since it was read: a heartbeat, a new
        delivery or its end since means its worker, or another, has it."""
        target = JobStatus.failed if give_up else JobStatus.accepted
        assert target in TRANSITIONS[JobStatus.running]
        sets: dict[str, Any] = {"status": target.value, "message": message, "worker_pid": None}
        if give_up:
            sets["finished"] = now()
        else:
            sets.update(requeues=job.requeues + 1, progress=0)
        if stored_bytes is not None:
            sets["stored_bytes"] = stored_bytes
        heartbeat = (jobs.c.heartbeat.is_(None) if job.heartbeat is None
                     else jobs.c.heartbeat == job.heartbeat)
        with self._transaction() as db:
            changed = db.execute(
                sa.update(jobs).where(
                    jobs.c.id == job.id, jobs.c.status == JobStatus.running.value,
                    jobs.c.attempts == job.attempts, jobs.c.requeues == job.requeues, heartbeat,
                ).values(**sets)
            ).rowcount
            if not changed:
                return None
            updated = db.execute(sa.select(jobs).where(jobs.c.id == job.id)).mappings().one()
        return Job.from_row(updated)

    def annotate(self, job_id: str, message: str) -> None:
        """Replace a job's message without changing its state (e.g. how a cancel ended)."""
        with self._transaction() as db:
            db.execute(sa.update(jobs).where(jobs.c.id == job_id).values(message=message))

    def status(self, job_id: str) -> JobStatus | None:
        with self._read() as db:
            status = db.execute(sa.select(jobs.c.status).where(jobs.c.id == job_id)).scalar()
        return JobStatus(status) if status is not None else None
