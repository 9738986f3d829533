"""Job records and API keys in one SQLite file under ``DATA_DIR`` (WAL mode).

The API and the worker processes open the same file; every write is one short transaction, so
they do not block each other for long. Keys are stored only as sha256 hashes.

:func:`Store.transition` is the one place that moves a job between states
(accepted -> running -> successful / failed / dismissed) and records failures.
"""

from __future__ import annotations

import hashlib
import json
import secrets
import sqlite3
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from datetime import UTC, datetime
from enum import StrEnum
from pathlib import Path
from typing import Any

from lidar_outliers.errors import LidarOutliersError


class StoreError(LidarOutliersError):
    """A user or job operation that cannot be done (unknown user, name taken, ...)."""


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
    # running -> running: a job re-delivered after its worker died starts again.
    JobStatus.running: {
        JobStatus.running,
        JobStatus.successful,
        JobStatus.failed,
        JobStatus.dismissed,
    },
    JobStatus.successful: {JobStatus.dismissed},
    JobStatus.failed: {JobStatus.dismissed},
    JobStatus.dismissed: set(),
}

SCHEMA = """
CREATE TABLE IF NOT EXISTS users (
    id INTEGER PRIMARY KEY,
    name TEXT NOT NULL UNIQUE,
    key_hash TEXT NOT NULL UNIQUE,
    created TEXT NOT NULL,
    revoked TEXT
);
CREATE TABLE IF NOT EXISTS jobs (
    id TEXT PRIMARY KEY,
    user_id INTEGER NOT NULL REFERENCES users(id),
    process_id TEXT NOT NULL,
    status TEXT NOT NULL,
    progress INTEGER NOT NULL DEFAULT 0,
    message TEXT NOT NULL DEFAULT '',
    created TEXT NOT NULL,
    started TEXT,
    finished TEXT,
    inputs TEXT NOT NULL,
    facts TEXT NOT NULL,
    laz INTEGER NOT NULL,
    attempts INTEGER NOT NULL DEFAULT 0,
    worker_pid INTEGER,
    stored_bytes INTEGER NOT NULL DEFAULT 0
);
CREATE INDEX IF NOT EXISTS jobs_by_user ON jobs(user_id, created);
CREATE TABLE IF NOT EXISTS uploads (
    id TEXT PRIMARY KEY,
    user_id INTEGER NOT NULL REFERENCES users(id),
    name TEXT NOT NULL,
    path TEXT NOT NULL,
    bytes INTEGER NOT NULL,
    created TEXT NOT NULL
);
"""


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
    path: str
    bytes: int
    created: str


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
    extra: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def from_row(cls, row: sqlite3.Row) -> Job:
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
            stored_bytes=row["stored_bytes"],
        )


class Store:
    """Users, uploads and jobs in SQLite. Cheap to create; opens one connection per operation."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with self._connect() as db:
            db.execute("PRAGMA journal_mode=WAL")
            db.executescript(SCHEMA)

    @contextmanager
    def _connect(self) -> Iterator[sqlite3.Connection]:
        db = sqlite3.connect(self.path, timeout=30.0, isolation_level=None)
        db.row_factory = sqlite3.Row
        db.execute("PRAGMA busy_timeout=30000")
        try:
            yield db
        finally:
            db.close()

    @contextmanager
    def _transaction(self) -> Iterator[sqlite3.Connection]:
        with self._connect() as db:
            db.execute("BEGIN IMMEDIATE")
            try:
                yield db
            except BaseException:
                db.execute("ROLLBACK")
                raise
            db.execute("COMMIT")

    # ---- users -------------------------------------------------------------------------------

    def add_user(self, name: str) -> tuple[User, str]:
        """Create a user and return it with its new key (the only time the key is visible)."""
        name = name.strip()
        if not name or len(name) > 100 or any(c.isspace() for c in name):
            raise StoreError(f"user name must be 1-100 characters without spaces, got {name!r}")
        key = "lo_" + secrets.token_urlsafe(32)
        created = now()
        with self._transaction() as db:
            if db.execute("SELECT 1 FROM users WHERE name = ?", (name,)).fetchone():
                raise StoreError(f"user {name!r} exists; revoke it first or choose another name")
            cur = db.execute(
                "INSERT INTO users (name, key_hash, created) VALUES (?, ?, ?)",
                (name, hash_key(key), created),
            )
            return User(id=cur.lastrowid or 0, name=name, created=created), key

    def list_users(self) -> list[User]:
        with self._connect() as db:
            rows = db.execute("SELECT id, name, created, revoked FROM users ORDER BY id").fetchall()
        return [User(**dict(r)) for r in rows]

    def revoke_user(self, name: str) -> None:
        """Invalidate a user's key. The name is freed (a new key can be issued under it) by
        renaming the revoked row; its jobs stay until retention deletes them."""
        with self._transaction() as db:
            row = db.execute(
                "SELECT id FROM users WHERE name = ? AND revoked IS NULL", (name,)
            ).fetchone()
            if row is None:
                raise StoreError(f"no active user named {name!r}")
            stamp = now()
            db.execute(
                "UPDATE users SET revoked = ?, name = ?, key_hash = ? WHERE id = ?",
                (stamp, f"{name}#revoked-{row['id']}", "revoked-" + secrets.token_hex(16),
                 row["id"]),
            )

    def user_for_key(self, key: str) -> User | None:
        with self._connect() as db:
            row = db.execute(
                "SELECT id, name, created, revoked FROM users WHERE key_hash = ? "
                "AND revoked IS NULL",
                (hash_key(key),),
            ).fetchone()
        return User(**dict(row)) if row else None

    # ---- uploads -----------------------------------------------------------------------------

    def add_upload(self, user_id: int, name: str, path: Path, size: int) -> Upload:
        upload = Upload(
            id=uuid.uuid4().hex, user_id=user_id, name=name, path=str(path), bytes=size,
            created=now(),
        )
        with self._transaction() as db:
            db.execute(
                "INSERT INTO uploads (id, user_id, name, path, bytes, created) "
                "VALUES (?, ?, ?, ?, ?, ?)",
                (upload.id, user_id, name, str(path), size, upload.created),
            )
        return upload

    def get_upload(self, upload_id: str, user_id: int) -> Upload | None:
        with self._connect() as db:
            row = db.execute(
                "SELECT * FROM uploads WHERE id = ? AND user_id = ?", (upload_id, user_id)
            ).fetchone()
        return Upload(**dict(row)) if row else None

    def delete_upload(self, upload_id: str) -> None:
        with self._transaction() as db:
            db.execute("DELETE FROM uploads WHERE id = ?", (upload_id,))

    def uploads_created_before(self, stamp: str) -> list[Upload]:
        with self._connect() as db:
            rows = db.execute("SELECT * FROM uploads WHERE created < ?", (stamp,)).fetchall()
        return [Upload(**dict(r)) for r in rows]

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
    ) -> Job:
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
        )
        with self._transaction() as db:
            db.execute(
                "INSERT INTO jobs (id, user_id, process_id, status, progress, message, created, "
                "inputs, facts, laz, stored_bytes) VALUES (?, ?, ?, ?, 0, ?, ?, ?, ?, ?, ?)",
                (job.id, user_id, process_id, job.status.value, job.message, job.created,
                 json.dumps(inputs), json.dumps(facts), int(laz), stored_bytes),
            )
        return job

    def get_job(self, job_id: str) -> Job | None:
        with self._connect() as db:
            row = db.execute("SELECT * FROM jobs WHERE id = ?", (job_id,)).fetchone()
        return Job.from_row(row) if row else None

    def list_jobs(self, user_id: int, limit: int, offset: int) -> tuple[list[Job], int]:
        """The user's jobs, newest first, and how many there are in all."""
        with self._connect() as db:
            rows = db.execute(
                "SELECT * FROM jobs WHERE user_id = ? ORDER BY created DESC, rowid DESC "
                "LIMIT ? OFFSET ?",
                (user_id, limit, offset),
            ).fetchall()
            total = db.execute(
                "SELECT COUNT(*) FROM jobs WHERE user_id = ?", (user_id,)
            ).fetchone()[0]
        return [Job.from_row(r) for r in rows], total

    def count_active(self, user_id: int) -> int:
        with self._connect() as db:
            return db.execute(
                "SELECT COUNT(*) FROM jobs WHERE user_id = ? AND status IN (?, ?)",
                (user_id, *[s.value for s in ACTIVE]),
            ).fetchone()[0]

    def stored_bytes(self, user_id: int) -> int:
        """Bytes the user keeps on the server: job folders and uploads."""
        with self._connect() as db:
            jobs = db.execute(
                "SELECT COALESCE(SUM(stored_bytes), 0) FROM jobs WHERE user_id = ?", (user_id,)
            ).fetchone()[0]
            uploads = db.execute(
                "SELECT COALESCE(SUM(bytes), 0) FROM uploads WHERE user_id = ?", (user_id,)
            ).fetchone()[0]
        return int(jobs) + int(uploads)

    def jobs_finished_before(self, stamp: str) -> list[Job]:
        with self._connect() as db:
            rows = db.execute(
                "SELECT * FROM jobs WHERE finished IS NOT NULL AND finished < ?", (stamp,)
            ).fetchall()
        return [Job.from_row(r) for r in rows]

    def delete_job(self, job_id: str) -> None:
        with self._transaction() as db:
            db.execute("DELETE FROM jobs WHERE id = ?", (job_id,))

    def transition(
        self,
        job_id: str,
        status: JobStatus,
        message: str | None = None,
        *,
        worker_pid: int | None = None,
        stored_bytes: int | None = None,
    ) -> Job | None:
        """Move a job to ``status`` if the move is allowed; return the job as stored afterwards,
        or None when the move is refused (unknown job, or already final such as dismissed)."""
        with self._transaction() as db:
            row = db.execute("SELECT * FROM jobs WHERE id = ?", (job_id,)).fetchone()
            if row is None:
                return None
            current = JobStatus(row["status"])
            if status not in TRANSITIONS[current]:
                return None
            sets = {"status": status.value}
            if message is not None:
                sets["message"] = message
            stamp = now()
            if status is JobStatus.running:
                sets["started"] = stamp
                sets["attempts"] = row["attempts"] + 1
                sets["worker_pid"] = worker_pid
                sets["progress"] = 0
            elif status in FINAL:
                sets["finished"] = stamp
                sets["worker_pid"] = None
            if status is JobStatus.successful:
                sets["progress"] = 100
            if stored_bytes is not None:
                sets["stored_bytes"] = stored_bytes
            assignments = ", ".join(f"{k} = ?" for k in sets)
            db.execute(f"UPDATE jobs SET {assignments} WHERE id = ?", (*sets.values(), job_id))
            row = db.execute("SELECT * FROM jobs WHERE id = ?", (job_id,)).fetchone()
        return Job.from_row(row)

    def set_progress(self, job_id: str, percent: int, message: str) -> JobStatus | None:
        """Record progress of a running job; return its status (the worker stops on dismissed)."""
        with self._transaction() as db:
            row = db.execute("SELECT status FROM jobs WHERE id = ?", (job_id,)).fetchone()
            if row is None:
                return None
            status = JobStatus(row["status"])
            if status is JobStatus.running:
                db.execute(
                    "UPDATE jobs SET progress = ?, message = ? WHERE id = ?",
                    (max(0, min(99, percent)), message, job_id),
                )
        return status

    def annotate(self, job_id: str, message: str) -> None:
        """Replace a job's message without changing its state (e.g. how a cancel ended)."""
        with self._transaction() as db:
            db.execute("UPDATE jobs SET message = ? WHERE id = ?", (message, job_id))

    def status(self, job_id: str) -> JobStatus | None:
        with self._connect() as db:
            row = db.execute("SELECT status FROM jobs WHERE id = ?", (job_id,)).fetchone()
        return JobStatus(row["status"]) if row else None
