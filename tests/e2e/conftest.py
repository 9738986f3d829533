"""Fixtures that start the real stack: one redis-server per session, stacks per module."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.e2e.stack import REDIS_SERVER, RedisServer

if not Path(REDIS_SERVER).exists():  # pragma: no cover - the machines we run on have it
    pytest.skip(f"{REDIS_SERVER} is needed for the end-to-end tests", allow_module_level=True)


@pytest.fixture(scope="session")
def redis_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[RedisServer]:
    server = RedisServer(tmp_path_factory.mktemp("redis"))
    yield server
    server.stop()
