"""`serve` when one of its processes dies: the others keep serving, the dead one is started
again, and the job a killed worker was running is queued again and finishes. Heartbeats every
second and a job stale after 5 s keep each test well under a minute."""

from __future__ import annotations

import json
import os
import signal
import subprocess
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import httpx
import psutil
import pytest

from lidar_outliers.jobs.store import Store
from tests.e2e.stack import free_port, wait_for, wait_job
from tests.e2e.test_serve import start_serve, stop_and_check, wait_ready
from tests.e2e.test_workers import SLOW
from tests.lasfiles import write_cloud

#: Enough points to be caught running (seconds of work), few enough to run twice in a minute.
POINTS = 100_000


@dataclass
class Served:
    proc: subprocess.Popen
    data_dir: Path
    port: int
    key: str
    log: Path

    def client(self) -> httpx.Client:
        return httpx.Client(base_url=f"http://127.0.0.1:{self.port}", timeout=60,
                            headers={"Authorization": f"Bearer {self.key}"})

    def programs(self) -> dict[str, int]:
        """Pids of the processes supervisord runs: redis, worker (its main process), api."""
        found = {}
        for child in psutil.Process(self.proc.pid).children(recursive=True):
            try:
                parent, command = child.parent(), " ".join(child.cmdline())
            except psutil.NoSuchProcess:
                continue
            if parent is None or "supervisord" not in " ".join(parent.cmdline()):
                continue  # the worker's pool
            for name, mark in (("redis", "redis-server"), ("worker", "celery"),
                               ("api", "uvicorn")):
                if mark in command and child.status() != psutil.STATUS_ZOMBIE:
                    found[name] = child.pid
        return found

    def restarted(self, name: str, old: int) -> dict[str, int]:
        """Until ``name`` runs again under a new pid; all pids then."""
        def check() -> dict[str, int] | None:
            now = self.programs()
            return now if now.get(name, old) != old and len(now) == 3 else None

        return wait_for(check, 30, f"{name} to be started again", interval=0.2)


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory, compiled_detectors: None
           ) -> Iterator[Served]:
    folder = tmp_path_factory.mktemp("served")
    port, log = free_port(), folder / "serve.log"
    proc = start_serve(folder / "data", port, log, heartbeat_interval_seconds=1,
                       stale_job_seconds=5, max_active_jobs_per_user=10)
    try:
        lines = wait_ready(proc, log, port).splitlines()
        key = lines[lines.index(next(x for x in lines if "development API key" in x)) + 1]
        yield Served(proc, folder / "data", port, key, log)
    finally:
        if proc.poll() is None:
            stop_and_check(proc, signal.SIGTERM)


def submit(served: Served, path: Path, inputs: dict | None = None) -> str:
    with served.client() as client:
        answer = client.post("/processes/pipeline/execution",
                             files={"file": (path.name, path.read_bytes())},
                             data={"inputs": json.dumps(inputs or {})})
    assert answer.status_code == 201, answer.text
    return answer.json()["jobID"]


def small_job_succeeds(served: Served, tmp_path: Path) -> None:
    path = tmp_path / "small.las"
    write_cloud(path, n=2000, seed=11)
    job = submit(served, path)
    with served.client() as client:
        done = wait_job(client, job, ("successful", "failed"), timeout=60)
    assert done["status"] == "successful", done["message"]


def test_the_worker_computes_on_the_cpus_shared_among_its_job_processes(served: Served) -> None:
    from lidar_outliers.cli.serve import threads_per_job

    expected = os.environ.get("NUMBA_NUM_THREADS") or str(threads_per_job(1))  # concurrency 1
    worker = psutil.Process(served.programs()["worker"])
    assert worker.environ()["NUMBA_NUM_THREADS"] == expected


def test_killed_worker_is_restarted_and_its_job_runs_again(served: Served,
                                                          tmp_path: Path) -> None:
    slow = tmp_path / "slow.las"
    write_cloud(slow, n=POINTS, seed=5)
    job = submit(served, slow, SLOW)
    store = Store(served.data_dir / "service.sqlite3", migrate=False)
    wait_for(lambda: (lambda j: j.status.value == "running" and j.worker_pid)(store.get_job(job)),
             60, "the job to run")
    before = served.programs()
    os.kill(before["worker"], signal.SIGKILL)  # the main process; its pool dies with it
    with served.client() as client:  # the API answers while the worker is away
        assert client.get(f"/jobs/{job}").status_code == 200
    after = served.restarted("worker", before["worker"])
    assert (after["redis"], after["api"]) == (before["redis"], before["api"])
    with served.client() as client:
        done = wait_job(client, job, ("successful", "failed"), timeout=90)
    assert done["status"] == "successful", done["message"]
    record = store.get_job(job)
    assert (record.attempts, record.requeues) == (2, 1)


def test_killed_redis_is_restarted_and_no_job_is_lost(served: Served, tmp_path: Path) -> None:
    slow, small = tmp_path / "slow.las", tmp_path / "small.las"
    write_cloud(slow, n=POINTS, seed=5)
    write_cloud(small, n=2000, seed=12)
    running = submit(served, slow, SLOW)
    queued = submit(served, small)  # waits in Redis behind the running one
    store = Store(served.data_dir / "service.sqlite3", migrate=False)
    wait_for(lambda: store.get_job(running).status.value == "running", 60, "the job to run")
    before = served.programs()
    os.kill(before["redis"], signal.SIGKILL)
    after = served.restarted("redis", before["redis"])
    assert (after["worker"], after["api"]) == (before["worker"], before["api"])
    with served.client() as client:
        for job in (running, queued):  # from Redis's append-only file, or queued again
            done = wait_job(client, job, ("successful", "failed"), timeout=90)
            assert done["status"] == "successful", done["message"]
    small_job_succeeds(served, tmp_path)  # and one sent after the restart
    assert served.programs() == after


def test_terminated_api_is_restarted(served: Served, tmp_path: Path) -> None:
    before = served.programs()
    os.kill(before["api"], signal.SIGTERM)
    after = served.restarted("api", before["api"])
    assert (after["redis"], after["worker"]) == (before["redis"], before["worker"])

    def answers() -> bool:
        try:
            with served.client() as client:
                return client.get("/jobs").status_code == 200
        except httpx.HTTPError:
            return False

    wait_for(answers, 30, "the API to answer again", interval=0.2)
    small_job_succeeds(served, tmp_path)


def test_sigterm_stops_every_process(served: Served) -> None:
    assert len(served.programs()) == 3
    stop_and_check(served.proc, signal.SIGTERM)  # exit code 0 and no process left
