"""Workers that lose nothing: SIGKILL mid-job, a job that kills its worker twice, cancellation of
a running job, and fairness between users. Real worker processes, real signals."""

from __future__ import annotations

import json
import os
import signal
from collections.abc import Iterator
from pathlib import Path

import laspy
import psutil
import pytest

from lidar_outliers.jobs.store import Store
from tests.e2e.stack import RedisServer, Stack, alive, running_stack, wait_for, wait_job
from tests.lasfiles import write_cloud

#: Long enough to be caught running on an idle machine too: temporal alone finishes 300 k points
#: in a tenth of a second, so a patch stage (about 50 k points/s) follows it.
SLOW_POINTS = 300_000
SLOW = {"pipeline": [{"detector": "temporal", "sigma": 0.01}, {"detector": "patch", "sigma": 0.01}]}


@pytest.fixture(scope="module")
def stack(redis_server: RedisServer, tmp_path_factory: pytest.TempPathFactory,
          compiled_detectors: None) -> Iterator[Stack]:
    # quick heartbeats and sweeps, so that a job of a vanished worker is queued again at once;
    # a time limit with room for a loaded machine (the redelivery is the sweep's, not Redis's)
    with running_stack(tmp_path_factory.mktemp("data"), redis_server.new_url(), workers=2,
                       max_active_jobs_per_user=10, task_time_limit=300,
                       visibility_timeout=320, heartbeat_interval_seconds=1,
                       stale_job_seconds=5) as s:
        yield s


@pytest.fixture(scope="module")
def key(stack: Stack) -> str:
    return stack.add_user("alice")


@pytest.fixture(scope="module")
def slow_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("in") / "slow.las"
    write_cloud(path, n=SLOW_POINTS, seed=5)
    return path


def submit(stack: Stack, key: str, path: Path, inputs: dict | None = None) -> str:
    with stack.client(key) as client:
        answer = client.post("/processes/pipeline/execution",
                             files={"file": (path.name, path.read_bytes())},
                             data={"inputs": json.dumps(inputs or {})})
        assert answer.status_code == 201, answer.text
        return answer.json()["jobID"]


def running_attempt(stack: Stack, job_id: str, attempt: int) -> int:
    """Wait until the job runs its ``attempt``-th delivery; return the pid running it."""
    store = Store(stack.data_dir / "service.sqlite3")

    def check() -> int | None:
        job = store.get_job(job_id)
        if job.status.value == "running" and job.attempts == attempt and job.worker_pid:
            return job.worker_pid
        return None

    return wait_for(check, 240, f"attempt {attempt} of job {job_id} to run", interval=0.05)


def test_sigkill_of_the_job_process_reruns_the_job(stack: Stack, key: str, slow_file: Path,
                                                   tmp_path: Path) -> None:
    job = submit(stack, key, slow_file, SLOW)
    pid = running_attempt(stack, job, 1)
    os.kill(pid, signal.SIGKILL)
    with stack.client(key) as client:
        done = wait_job(client, job, ("successful", "failed"), timeout=300)
        assert done["status"] == "successful", done["message"]
        out = tmp_path / "out.las"
        out.write_bytes(client.get(f"/jobs/{job}/results/cloud").content)
    assert Store(stack.data_dir / "service.sqlite3").get_job(job).attempts == 2
    las = laspy.read(out)
    assert len(las.points) == SLOW_POINTS
    assert "temporal_score" in las.point_format.extra_dimension_names
    assert not list((stack.data_dir / "jobs" / job).glob("*.tmp*"))


def test_job_that_kills_its_worker_twice_fails_and_others_succeed(
    stack: Stack, key: str, slow_file: Path, tmp_path: Path
) -> None:
    job = submit(stack, key, slow_file, SLOW)
    for attempt in (1, 2):
        os.kill(running_attempt(stack, job, attempt), signal.SIGKILL)
    small = tmp_path / "small.las"
    write_cloud(small, n=2000, seed=6)
    other = submit(stack, key, small)
    with stack.client(key) as client:
        failed = wait_job(client, job, ("successful", "failed"), timeout=300)
        assert failed["status"] == "failed"
        assert "died 2 times" in failed["message"]
        assert client.get(f"/jobs/{job}/results/cloud").status_code == 404
        assert wait_job(client, other, ("successful", "failed"))["status"] == "successful"
    # both workers are still serving
    stack.wait_workers_ready(timeout=60)
    assert all(w.poll() is None for w in stack.workers)


def test_whole_worker_killed_job_is_redelivered_to_another(
    stack: Stack, key: str, slow_file: Path
) -> None:
    job = submit(stack, key, slow_file, SLOW)
    pid = running_attempt(stack, job, 1)
    leader = psutil.Process(pid).parent()
    victim = next(w for w in stack.workers if w.pid == leader.pid)
    group = [leader.pid, *(p.pid for p in leader.children(recursive=True))]
    os.killpg(victim.pid, signal.SIGKILL)  # the worker and its pool vanish at once
    victim.wait()
    wait_for(lambda: not alive(group), 10, "the killed worker's processes to go")
    with stack.client(key) as client:
        done = wait_job(client, job, ("successful", "failed"), timeout=300)
    assert done["status"] == "successful", done["message"]
    record = Store(stack.data_dir / "service.sqlite3").get_job(job)
    assert (record.attempts, record.requeues) == (2, 1)  # queued again by the other's sweep
    stack.workers.remove(victim)
    stack.start_worker()  # back to two for the tests that follow
    stack.wait_workers_ready()


def test_cancel_a_running_job(stack: Stack, key: str, slow_file: Path) -> None:
    job = submit(stack, key, slow_file, SLOW)
    running_attempt(stack, job, 1)
    with stack.client(key) as client:
        # progress is reported while the job runs
        seen = wait_for(lambda: (lambda d: d if 0 < d["progress"] < 100 else None)(
            client.get(f"/jobs/{job}").json()), 120, "progress above 0 %", interval=0.05)
        assert seen["status"] == "running" and seen["message"]
        answer = client.delete(f"/jobs/{job}")
        assert answer.status_code == 200
        assert answer.json()["status"] == "dismissed"
        # the worker notices at its next progress report, stops and removes its files
        wait_for(lambda: "worker stopped" in client.get(f"/jobs/{job}").json()["message"],
                 240, "the worker to stop the dismissed job")
        doc = client.get(f"/jobs/{job}").json()
        assert doc["status"] == "dismissed"
        assert not (stack.data_dir / "jobs" / job).exists()
        assert client.get(f"/jobs/{job}/results/cloud").status_code == 404


@pytest.fixture(scope="module")
def single_worker(redis_server: RedisServer, tmp_path_factory: pytest.TempPathFactory,
                  compiled_detectors: None) -> Iterator[Stack]:
    with running_stack(tmp_path_factory.mktemp("fair"), redis_server.new_url(),
                       max_active_jobs_per_user=10) as s:
        yield s


def test_one_users_queue_does_not_starve_another(single_worker: Stack, tmp_path: Path) -> None:
    stack = single_worker
    alice, bob = stack.add_user("alice"), stack.add_user("bob")
    path = tmp_path / "mid.las"
    write_cloud(path, n=8000, seed=7)
    inputs = {"pipeline": [{"detector": "patch", "sigma": 0.01}]}
    a_jobs = [submit(stack, alice, path, inputs) for _ in range(5)]
    b_job = submit(stack, bob, path, inputs)
    store = Store(stack.data_dir / "service.sqlite3")
    with stack.client(alice) as client:
        for job in a_jobs:
            assert wait_job(client, job, ("successful", "failed"))["status"] == "successful"
    with stack.client(bob) as client:
        assert wait_job(client, b_job, ("successful", "failed"))["status"] == "successful"
    b = store.get_job(b_job)
    a_started = sorted(store.get_job(job).started for job in a_jobs)
    # no job of alice's started while bob's waited: bob's went ahead of her queue ...
    assert not [t for t in a_started if b.created < t < b.started], (b.created, b.started,
                                                                     a_started)
    # ... and her last ones ran after it
    assert sum(t > b.started for t in a_started) >= 2, (b.started, a_started)
