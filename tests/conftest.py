"""Session fixtures for the real back ends (tests/backends.py): started only by the tests that
ask for them."""

from __future__ import annotations

import os
from collections.abc import Iterator

import pytest

from tests.backends import S3_ENV, MotoServer, Postgres


@pytest.fixture(scope="session")
def postgres() -> Iterator[Postgres]:
    server = Postgres.connect_or_give_up()
    yield server
    server.close()


@pytest.fixture(scope="session")
def postgres_url(postgres: Postgres) -> Iterator[str]:
    """A database made for this session (dropped at its end), shared by the tests that clear
    its tables (tests.backends.clear)."""
    with postgres.database() as url:
        yield url


@pytest.fixture(scope="session")
def moto(tmp_path_factory: pytest.TempPathFactory) -> Iterator[MotoServer]:
    """moto's S3 server; boto3 in this process finds its credentials in the environment."""
    saved = {k: os.environ.get(k) for k in S3_ENV}
    os.environ.update(S3_ENV)
    server = MotoServer(tmp_path_factory.mktemp("moto"))
    yield server
    server.stop()
    for k, v in saved.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v
