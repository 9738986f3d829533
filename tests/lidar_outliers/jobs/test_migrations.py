"""Schema migrations: a new database reaches the schema of lidar_outliers.jobs.schema; a database
of the store before migrations is adopted with its records; starts at the same moment do not
race; every migration can be undone."""

from __future__ import annotations

import multiprocessing
import sqlite3
from collections.abc import Iterator
from pathlib import Path

import pytest
import sqlalchemy as sa
from alembic import command
from alembic.autogenerate import compare_metadata
from alembic.migration import MigrationContext

from lidar_outliers.jobs import database
from lidar_outliers.jobs.schema import metadata
from lidar_outliers.jobs.store import JobStatus, Store

#: The tables the store created itself before it had migrations (revision 0001's schema).
LEGACY_SCHEMA = """
CREATE TABLE users (id INTEGER PRIMARY KEY, name TEXT NOT NULL UNIQUE,
    key_hash TEXT NOT NULL UNIQUE, created TEXT NOT NULL, revoked TEXT);
CREATE TABLE jobs (id TEXT PRIMARY KEY, user_id INTEGER NOT NULL REFERENCES users(id),
    process_id TEXT NOT NULL, status TEXT NOT NULL, progress INTEGER NOT NULL DEFAULT 0,
    message TEXT NOT NULL DEFAULT '', created TEXT NOT NULL, started TEXT, finished TEXT,
    inputs TEXT NOT NULL, facts TEXT NOT NULL, laz INTEGER NOT NULL,
    attempts INTEGER NOT NULL DEFAULT 0, worker_pid INTEGER,
    stored_bytes INTEGER NOT NULL DEFAULT 0);
CREATE INDEX jobs_by_user ON jobs(user_id, created);
CREATE TABLE uploads (id TEXT PRIMARY KEY, user_id INTEGER NOT NULL REFERENCES users(id),
    name TEXT NOT NULL, path TEXT NOT NULL, bytes INTEGER NOT NULL, created TEXT NOT NULL);
"""


@pytest.fixture(params=["sqlite", "postgresql"])
def empty_url(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[str]:
    """A database without any table."""
    if request.param == "sqlite":
        yield f"sqlite:///{tmp_path / 'service.sqlite3'}"
        return
    with request.getfixturevalue("postgres").database() as url:
        yield url


def schema_differences(engine: sa.Engine) -> list:
    with engine.connect() as db:
        context = MigrationContext.configure(db, opts={"compare_type": True})
        return [d for d in compare_metadata(context, metadata)
                if not (d[0] == "remove_table" and d[1].name == "alembic_version")]


def test_a_new_database_gets_the_schema_of_the_code(empty_url: str) -> None:
    engine = database.create_engine(empty_url)
    try:
        assert database.current(engine) is None
        database.upgrade(engine)
        assert database.current(engine) == database.head() == "0005"
        assert schema_differences(engine) == []
        database.upgrade(engine)  # again: nothing to do
        assert database.current(engine) == database.head()
    finally:
        engine.dispose()


def test_every_migration_can_be_undone(empty_url: str) -> None:
    engine = database.create_engine(empty_url)
    try:
        database.upgrade(engine)
        with engine.begin() as db:
            command.downgrade(database.alembic_config(db), "base")
        assert set(sa.inspect(engine).get_table_names()) <= {"alembic_version"}
        database.upgrade(engine)
        assert schema_differences(engine) == []
    finally:
        engine.dispose()


def _upgrade(url: str) -> None:
    engine = database.create_engine(url)
    database.upgrade(engine)
    engine.dispose()


def test_starts_at_the_same_moment_migrate_once(empty_url: str) -> None:
    """Eight processes open a new database at once: all succeed, the schema is made once."""
    # spawned, not forked: a fork copies locks other threads of the test run hold (a hang)
    spawn = multiprocessing.get_context("spawn")
    starters = [spawn.Process(target=_upgrade, args=(empty_url,)) for _ in range(8)]
    for p in starters:
        p.start()
    for p in starters:
        p.join(timeout=120)
        if p.exitcode is None:
            p.kill()
    assert [p.exitcode for p in starters] == [0] * 8
    engine = database.create_engine(empty_url)
    try:
        with engine.connect() as db:
            assert db.execute(sa.text("SELECT version_num FROM alembic_version")).all() == [
                (database.head(),)]
        assert schema_differences(engine) == []
    finally:
        engine.dispose()


def test_a_database_from_before_migrations_is_adopted(tmp_path: Path) -> None:
    """The SQLite file of the store before it had migrations: stamped at 0001, migrated, every
    record kept; uploads are named by storage key; jobs keep their order."""
    path = tmp_path / "service.sqlite3"
    db = sqlite3.connect(path)
    db.executescript(LEGACY_SCHEMA)
    db.execute("INSERT INTO users VALUES (1, 'alice', 'h1', '2024-01-01T00:00:00.000Z', NULL)")
    db.execute("INSERT INTO users VALUES (2, 'bob', 'h2', '2024-01-01T00:00:00.000Z', NULL)")
    same_time = "2024-01-02T00:00:00.000Z"
    for job_id, user in (("b", 1), ("a", 1), ("c", 2), ("d", 1)):  # ties broken by insertion
        db.execute("INSERT INTO jobs (id, user_id, process_id, status, created, inputs, facts, "
                   "laz, stored_bytes) VALUES (?, ?, 'temporal', 'successful', ?, '{}', "
                   "'{\"points\": 3}', 1, 7)", (job_id, user, same_time))
    db.execute("INSERT INTO uploads VALUES ('u1', 1, 'scan.las', ?, 99, ?)",
               (str(tmp_path / "data" / "uploads" / "1" / "u1.las"), same_time))
    db.commit()
    db.close()

    store = Store(path)
    try:
        assert database.current(store.engine) == database.head()
        jobs, total = store.list_jobs(1, 10, 0)
        assert total == 3 and [j.id for j in jobs] == ["d", "a", "b"]
        assert [j.seq for j in jobs] == [3, 2, 1]
        assert jobs[0].laz is True and jobs[0].facts == {"points": 3}
        upload = store.get_upload("u1", 1)
        assert upload.key == "uploads/1/u1.las" and upload.facts is None
        assert store.stored_bytes(1) == 3 * 7 + 99
        job = store.create_job(1, "patch", {}, {}, False, 1)
        assert job.seq == 4
        assert store.transition("d", JobStatus.dismissed) is not None
    finally:
        store.close()
