"""Fixtures that start the real stack: one redis-server per session, stacks per module.

Without a redis-server that starts, every test here fails when the ``CI`` environment variable is
set (as .ci/run sets it) and is skipped otherwise, with the reason either way.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from typing import NoReturn

import pytest

from tests.e2e.stack import REDIS_SERVER, RedisServer


def unavailable(reason: str) -> NoReturn:
    """Fail under CI, skip elsewhere; the message says what is missing and how to install it."""
    message = (f"the end-to-end tests need redis-server: {reason} "
               "(install it with `apt install redis-server`)")
    if os.environ.get("CI"):
        pytest.fail(message, pytrace=False)
    pytest.skip(message)


@pytest.fixture(scope="session", autouse=True)
def redis_installed() -> None:
    """Every test here needs the redis-server binary, `serve` included."""
    if not os.access(REDIS_SERVER, os.X_OK):
        unavailable(f"{REDIS_SERVER} not found")


@pytest.fixture(scope="session")
def redis_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[RedisServer]:
    try:
        server = RedisServer(tmp_path_factory.mktemp("redis"))
    except (OSError, AssertionError) as err:
        unavailable(f"{REDIS_SERVER} did not start: {err}")
    yield server
    server.stop()


WARM_UP = """
import sys, tempfile, pathlib
from tests.lasfiles import write_cloud
from lidar_outliers.process import process_file
folder = pathlib.Path(tempfile.mkdtemp())
write_cloud(folder / "in.las", n=3000)
for pipeline in (None, [{"detector": "temporal", "sigma": 0.01}], [{"detector": "section"}],
                 [{"detector": "patch", "sigma": 0.01}, {"detector": "section"}]):
    process_file(folder / "in.las", folder / "out.las", {"pipeline": pipeline})
from algorithms.temporal.compiled import load
load()  # the compiled smoother, which a stream of a long file or a tiled pre-pass takes
"""


@pytest.fixture(scope="session")
def compiled_detectors() -> None:
    """Compile the numba kernels once (cached on disk) before workers with time limits start."""
    import subprocess
    import sys

    from tests.e2e.stack import ROOT

    subprocess.run([sys.executable, "-c", WARM_UP], cwd=ROOT, check=True, timeout=900)
