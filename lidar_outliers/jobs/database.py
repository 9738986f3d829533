"""The job store's database: engines for SQLite and PostgreSQL, and schema migrations.

:func:`upgrade` brings a database to the newest schema with Alembic. The API, every worker and
``lidar-outliers users`` call it when they start, possibly at the same moment on several hosts,
so it runs under a lock: a PostgreSQL advisory lock held by the migrating transaction, or an
exclusive lock on a file beside the SQLite database. Whoever comes second finds the schema new
and does nothing.

SQLite transactions that write begin with ``BEGIN IMMEDIATE`` (the database's write lock is
taken at the start), so a check and the write that depends on it cannot interleave with
another writer's; reads begin with a plain ``BEGIN`` and never wait for writers (WAL).
"""

from __future__ import annotations

import fcntl
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import sqlalchemy as sa
from alembic import command
from alembic.config import Config
from alembic.runtime.migration import MigrationContext
from alembic.script import ScriptDirectory

MIGRATIONS = Path(__file__).with_name("migrations")
#: The revision whose schema the store had before it had migrations.
BASELINE = "0001"
#: Key of the PostgreSQL advisory lock that serialises migrations (any constant; 'lidarout').
ADVISORY_LOCK = 0x6C6964_61726F7574
#: Execution option of a connection whose SQLite transaction must take the write lock at once.
WRITE = "lidar_outliers_write"
BUSY_TIMEOUT_MS = 30_000


def normalise_url(url: str | Path) -> sa.URL:
    """A SQLAlchemy URL; a plain path means a SQLite file, ``postgresql://`` means psycopg 3."""
    if isinstance(url, Path) or "://" not in url:
        return sa.make_url(f"sqlite:///{Path(url).resolve()}")
    parsed = sa.make_url(url)
    if parsed.drivername in ("postgresql", "postgres"):
        parsed = parsed.set(drivername="postgresql+psycopg")
    return parsed


def sqlite_file(url: sa.URL) -> Path | None:
    """The database file of a SQLite URL (None for other databases or in-memory SQLite)."""
    if url.get_backend_name() != "sqlite" or url.database in (None, "", ":memory:"):
        return None
    return Path(url.database)


def create_engine(url: str | Path) -> sa.Engine:
    """An engine for the store's database; SQLite gets its folder, a busy timeout and explicit
    transactions (see the module's docstring)."""
    parsed = normalise_url(url)
    if parsed.get_backend_name() != "sqlite":
        # pre-ping: a database restarted behind the pool does not fail the next request
        return sa.create_engine(parsed, pool_pre_ping=True)
    path = sqlite_file(parsed)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
    engine = sa.create_engine(parsed, connect_args={"timeout": BUSY_TIMEOUT_MS / 1000})

    @sa.event.listens_for(engine, "connect")
    def _on_connect(dbapi_connection: Any, _record: Any) -> None:
        # the driver's own transaction handling off: the "begin" hook below decides
        dbapi_connection.isolation_level = None
        cursor = dbapi_connection.cursor()
        cursor.execute(f"PRAGMA busy_timeout={BUSY_TIMEOUT_MS}")
        cursor.close()

    @sa.event.listens_for(engine, "begin")
    def _on_begin(connection: sa.Connection) -> None:
        write = connection.get_execution_options().get(WRITE, False)
        connection.exec_driver_sql("BEGIN IMMEDIATE" if write else "BEGIN")

    return engine


def alembic_config(connection: sa.Connection | None = None) -> Config:
    """Alembic's configuration without an ini file: the migrations inside this package."""
    config = Config()
    config.set_main_option("script_location", str(MIGRATIONS))
    if connection is not None:
        config.attributes["connection"] = connection
    return config


def head() -> str:
    """The newest revision."""
    revision = ScriptDirectory.from_config(alembic_config()).get_current_head()
    assert revision is not None
    return revision


def current(engine: sa.Engine) -> str | None:
    """The database's revision (None before the first migration)."""
    with engine.connect() as connection:
        return MigrationContext.configure(connection).get_current_revision()


def upgrade(engine: sa.Engine) -> None:
    """Migrate the database to the newest schema, safely when several processes start at once."""
    with _migration_lock(engine), engine.connect() as connection:
        connection = connection.execution_options(**{WRITE: True})
        with connection.begin():
            if connection.dialect.name == "postgresql":
                # held until this transaction ends; PostgreSQL migrates inside it (DDL is
                # transactional), so a second process sees either nothing or all of it
                connection.execute(sa.text("SELECT pg_advisory_xact_lock(:key)"),
                                   {"key": ADVISORY_LOCK})
            tables = set(sa.inspect(connection).get_table_names())
            config = alembic_config(connection)
            if "alembic_version" not in tables and "jobs" in tables:
                command.stamp(config, BASELINE)  # made by the store before migrations
            command.upgrade(config, "head")


@contextmanager
def _migration_lock(engine: sa.Engine) -> Iterator[None]:
    """An exclusive lock on ``<database>.lock`` for SQLite (WAL mode is switched on under it);
    nothing for other databases, which lock inside the migrating transaction."""
    path = sqlite_file(engine.url)
    if path is None:
        yield
        return
    with open(path.with_name(path.name + ".lock"), "a+b") as lock:
        fcntl.flock(lock.fileno(), fcntl.LOCK_EX)
        try:
            # persistent in the file; set outside any transaction (the driver autocommits)
            raw = engine.raw_connection()
            try:
                raw.cursor().execute("PRAGMA journal_mode=WAL")
            finally:
                raw.close()
            yield
        finally:
            fcntl.flock(lock.fileno(), fcntl.LOCK_UN)


def describe(url: str | Path) -> str:
    """The database's URL without its password, for messages."""
    parsed = normalise_url(url)
    return parsed.render_as_string(hide_password=True)

