"""The job store's tables as SQLAlchemy Core metadata: the schema the migrations lead to.

The same definitions serve SQLite and PostgreSQL. Times are ISO 8601 text in UTC with a ``Z``
(fixed width, so they sort as text); ``inputs`` and ``facts`` are JSON text. Byte counts are
64-bit integers (SQLite's INTEGER is 64-bit already). A change here needs a migration in
``migrations/versions`` that leads to it; ``tests/lidar_outliers/jobs/test_migrations.py``
compares the two.
"""

from __future__ import annotations

import sqlalchemy as sa

#: 64-bit integer on PostgreSQL; plain INTEGER (64-bit) on SQLite, as the tables always had.
Bytes = sa.BigInteger().with_variant(sa.Integer(), "sqlite")

metadata = sa.MetaData()

users = sa.Table(
    "users",
    metadata,
    sa.Column("id", sa.Integer, primary_key=True),
    sa.Column("name", sa.Text, nullable=False, unique=True),
    sa.Column("key_hash", sa.Text, nullable=False, unique=True),
    sa.Column("created", sa.Text, nullable=False),
    sa.Column("revoked", sa.Text),
)

jobs = sa.Table(
    "jobs",
    metadata,
    sa.Column("id", sa.Text, primary_key=True),
    sa.Column("user_id", sa.Integer, sa.ForeignKey("users.id"), nullable=False),
    sa.Column("process_id", sa.Text, nullable=False),
    sa.Column("status", sa.Text, nullable=False),
    sa.Column("progress", sa.Integer, nullable=False, server_default=sa.text("0")),
    sa.Column("message", sa.Text, nullable=False, server_default=""),
    sa.Column("created", sa.Text, nullable=False),
    sa.Column("started", sa.Text),
    sa.Column("finished", sa.Text),
    sa.Column("inputs", sa.Text, nullable=False),
    sa.Column("facts", sa.Text, nullable=False),
    sa.Column("laz", sa.Integer, nullable=False),
    sa.Column("attempts", sa.Integer, nullable=False, server_default=sa.text("0")),
    sa.Column("worker_pid", sa.Integer),
    # the running delivery's last sign of life and its host (a vanished worker's job is re-queued)
    sa.Column("heartbeat", sa.Text),
    sa.Column("worker_host", sa.Text),
    # times the job was put back in the queue after its worker vanished; older messages are stale
    sa.Column("requeues", sa.Integer, nullable=False, server_default=sa.text("0")),
    sa.Column("stored_bytes", Bytes, nullable=False, server_default=sa.text("0")),
    # the user's n-th job: lists keep submission order whatever the hosts' clocks say
    sa.Column("seq", sa.Integer, nullable=False, server_default=sa.text("0")),
    # the callback URIs of the execute request as JSON (NULL: none)
    sa.Column("subscriber", sa.Text),
    sa.Index("jobs_by_user_seq", "user_id", "seq", unique=True),
    sa.Index("jobs_by_user_status", "user_id", "status"),
)

uploads = sa.Table(
    "uploads",
    metadata,
    sa.Column("id", sa.Text, primary_key=True),
    sa.Column("user_id", sa.Integer, sa.ForeignKey("users.id"), nullable=False),
    sa.Column("name", sa.Text, nullable=False),
    # where the file is in the object storage (lidar_outliers.jobs.storage)
    sa.Column("key", sa.Text, nullable=False),
    sa.Column("bytes", Bytes, nullable=False),
    sa.Column("created", sa.Text, nullable=False),
    # header facts of a cloud or a trajectory's summary, so a job can use it without reading it
    sa.Column("facts", sa.Text),
)

resumable_uploads = sa.Table(
    "resumable_uploads",
    metadata,
    # the id the upload keeps in ``uploads`` once its last byte has arrived
    sa.Column("id", sa.Text, primary_key=True),
    sa.Column("user_id", sa.Integer, sa.ForeignKey("users.id"), nullable=False),
    sa.Column("name", sa.Text, nullable=False),
    # cloud or trajectory, as for POST /uploads?kind=
    sa.Column("kind", sa.Text, nullable=False),
    # the announced size: reserved against the user's quota from the start
    sa.Column("length", Bytes, nullable=False),
    # bytes received and on disk (fsync'd); a PATCH continues here
    sa.Column("offset", Bytes, nullable=False, server_default=sa.text("0")),
    sa.Column("created", sa.Text, nullable=False),
    # unfinished uploads are deleted after this time (moved on by every PATCH)
    sa.Column("expires", sa.Text, nullable=False),
    # the host whose disk holds the partial data
    sa.Column("host", sa.Text, nullable=False),
    sa.Index("resumable_uploads_by_expiry", "expires"),
)
