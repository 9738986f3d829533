"""Real back ends for the tests: PostgreSQL databases made for this test session, and an S3
server (moto's server mode) started as a process of its own.

PostgreSQL is the server at ``TEST_POSTGRES_URL`` (default: postgres on 127.0.0.1:5432, which
``apt install postgresql`` gives); each session makes its own databases and drops them at the
end. Without a server (or moto), a test that needs one fails when the ``CI`` environment
variable is set and is skipped otherwise, with the reason either way.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, NoReturn

import pytest
import sqlalchemy as sa

DEFAULT_POSTGRES = "postgresql://postgres@127.0.0.1:5432/postgres"
MOTO_SERVER = Path(sys.executable).parent / "moto_server"
#: moto accepts any credentials; boto3 needs some.
S3_ENV = {"AWS_ACCESS_KEY_ID": "testing", "AWS_SECRET_ACCESS_KEY": "testing",
          "AWS_DEFAULT_REGION": "us-east-1"}


def unavailable(message: str) -> NoReturn:
    """Fail under CI, skip elsewhere; ``message`` says what is missing and how to get it."""
    if os.environ.get("CI"):
        pytest.fail(message, pytrace=False)
    pytest.skip(message)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Postgres:
    """A PostgreSQL server on which the tests create (and drop) databases of their own."""

    def __init__(self, admin_url: str) -> None:
        self.admin_url = sa.make_url(admin_url).set(drivername="postgresql+psycopg")
        self.engine = sa.create_engine(self.admin_url, isolation_level="AUTOCOMMIT",
                                       poolclass=sa.NullPool)
        with self.engine.connect() as db:
            db.execute(sa.text("SELECT 1"))

    @classmethod
    def connect_or_give_up(cls) -> Postgres:
        url = os.environ.get("TEST_POSTGRES_URL", DEFAULT_POSTGRES)
        shown = sa.make_url(url).render_as_string(hide_password=True)
        try:
            return cls(url)
        except Exception as exc:  # whatever stops the connection is the reason
            reason = str(getattr(exc, "orig", None) or exc).strip().splitlines()[0]
            unavailable(f"these tests need PostgreSQL at {shown} (TEST_POSTGRES_URL): {reason} "
                        "(install it with `apt install postgresql`)")

    def create(self) -> str:
        """A new empty database; its URL."""
        name = f"lidar_outliers_test_{os.getpid()}_{uuid.uuid4().hex[:8]}"
        with self.engine.connect() as db:
            db.execute(sa.text(f'CREATE DATABASE "{name}"'))
        return self.admin_url.set(database=name).render_as_string(hide_password=False)

    def drop(self, url: str) -> None:
        name = sa.make_url(url).database
        with self.engine.connect() as db:
            db.execute(sa.text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))

    @contextmanager
    def database(self) -> Iterator[str]:
        url = self.create()
        try:
            yield url
        finally:
            self.drop(url)

    def close(self) -> None:
        self.engine.dispose()


def clear(url: str) -> None:
    """Empty the store's tables (the schema stays), for the next test on the same database."""
    engine = sa.create_engine(sa.make_url(url).set(drivername="postgresql+psycopg"),
                              poolclass=sa.NullPool)
    with engine.begin() as db:
        tables = set(sa.inspect(db).get_table_names()) & {"users", "jobs", "uploads"}
        if tables:
            db.execute(sa.text(f"TRUNCATE {', '.join(sorted(tables))} RESTART IDENTITY CASCADE"))
    engine.dispose()


class MotoServer:
    """moto's S3 server on a free port of 127.0.0.1, in its own process group."""

    def __init__(self, folder: Path) -> None:
        if not os.access(MOTO_SERVER, os.X_OK):
            unavailable(f"these tests need moto's S3 server: {MOTO_SERVER} not found "
                        '(install it with `pip install "moto[server]"`, part of `make install`)')
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.log = folder / "moto.log"
        with open(self.log, "ab") as log:
            self.proc = subprocess.Popen(
                [str(MOTO_SERVER), "-H", "127.0.0.1", "-p", str(self.port)],
                stdout=log, stderr=subprocess.STDOUT, start_new_session=True,
                env=dict(os.environ, **S3_ENV),
            )
        deadline = time.monotonic() + 60
        while True:
            if self.proc.poll() is not None:
                unavailable(f"moto_server exited with {self.proc.returncode}: "
                            f"{self.log.read_text()[-500:]}")
            try:
                with socket.create_connection(("127.0.0.1", self.port), timeout=0.2):
                    break
            except OSError:
                if time.monotonic() > deadline:
                    self.stop()
                    unavailable(f"moto_server did not listen on {self.port} within 60 s")
                time.sleep(0.1)

    def client(self) -> Any:
        """A boto3 S3 client of this server."""
        import boto3

        return boto3.client("s3", endpoint_url=self.url,
                            aws_access_key_id=S3_ENV["AWS_ACCESS_KEY_ID"],
                            aws_secret_access_key=S3_ENV["AWS_SECRET_ACCESS_KEY"],
                            region_name=S3_ENV["AWS_DEFAULT_REGION"])

    def new_bucket(self) -> str:
        name = f"lidar-{uuid.uuid4().hex[:12]}"
        self.client().create_bucket(Bucket=name)
        return name

    def stop(self) -> None:
        try:
            os.killpg(self.proc.pid, signal.SIGTERM)
            self.proc.wait(timeout=20)
        except (ProcessLookupError, subprocess.TimeoutExpired):
            try:
                os.killpg(self.proc.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            self.proc.wait()
