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


WARM_UP = """
import sys, tempfile, pathlib
from tests.e2e.clouds import write_cloud
from lidar_outliers.process import process_file
folder = pathlib.Path(tempfile.mkdtemp())
write_cloud(folder / "in.las", n=3000)
for pipeline in (None, [{"detector": "temporal", "sigma": 0.01}], [{"detector": "section"}],
                 [{"detector": "patch", "sigma": 0.01}, {"detector": "section"}]):
    process_file(folder / "in.las", folder / "out.las", {"pipeline": pipeline})
"""


@pytest.fixture(scope="session")
def compiled_detectors() -> None:
    """Compile the numba kernels once (cached on disk) before workers with time limits start."""
    import subprocess
    import sys

    from tests.e2e.stack import ROOT

    subprocess.run([sys.executable, "-c", WARM_UP], cwd=ROOT, check=True, timeout=900)
