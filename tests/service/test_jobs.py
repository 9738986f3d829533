"""Service logic without HTTP: submission, the worker's job run, retention. Real LAS files."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from datetime import UTC, datetime, timedelta
from pathlib import Path

import laspy
import numpy as np
import pytest

from lidar_outliers.jobs import layout
from lidar_outliers.jobs.execute import execute_job
from lidar_outliers.jobs.settings import Settings
from lidar_outliers.jobs.store import JobStatus, Store
from service.jobs import JobService
from service.problems import Problem
from tests.lasfiles import write_cloud

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def settings(tmp_path: Path) -> Settings:
    return Settings(data_dir=tmp_path / "data", max_active_jobs_per_user=3)


@pytest.fixture
def store(settings: Settings) -> Store:
    return Store(settings.db_path)


@pytest.fixture
def queued() -> list[tuple[str, int]]:
    return []


@pytest.fixture
def service(settings: Settings, store: Store, queued: list) -> JobService:
    # the queue is a list here; tests/e2e run the same code against Celery and Redis
    return JobService(settings, store, enqueue=lambda job_id, p: queued.append((job_id, p)))


def submit(service: JobService, user, tmp_path: Path, name: str = "scan.las", **kwargs):
    path = tmp_path / name
    spikes = write_cloud(path, n=1500, **kwargs)
    params, _ = service.parse_inputs("temporal", {"sigma": 0.01})
    return service.submit(user, "temporal", params, path, name, move=True), spikes


def test_priority_is_the_users_number_of_active_jobs(service, store, queued, tmp_path) -> None:
    alice, _ = store.add_user("alice")
    bob, _ = store.add_user("bob")
    for i in range(3):
        submit(service, alice, tmp_path, f"a{i}.las")
    submit(service, bob, tmp_path, "b.las")
    assert [p for _, p in queued] == [0, 1, 2, 0]
    with pytest.raises(Problem) as caught:
        submit(service, alice, tmp_path, "a3.las")
    assert caught.value.status == 429 and "Retry-After" in caught.value.headers
    assert not (tmp_path / "a3.las").exists()  # the refused upload is not kept


def test_worker_run_writes_result_and_statistics(service, store, settings, tmp_path) -> None:
    alice, _ = store.add_user("alice")
    job, spikes = submit(service, alice, tmp_path)
    assert execute_job(settings, store, job.id) is JobStatus.successful
    done = store.get_job(job.id)
    assert done.status is JobStatus.successful and done.progress == 100
    assert done.stored_bytes > 0
    las = laspy.read(layout.result_path(settings, job.id, False))
    assert set(spikes) <= set(np.flatnonzero(np.asarray(las.outlier_flags)))
    stats = json.loads(layout.statistics_path(settings, job.id).read_text())
    assert "temporal" in json.dumps(stats)
    assert stats["input"]["name"] == "scan.las"
    # a late re-delivery of a finished job does nothing
    assert execute_job(settings, store, job.id) is None


def test_worker_failure_is_recorded_with_its_message(service, store, settings, tmp_path):
    alice, _ = store.add_user("alice")
    job, _ = submit(service, alice, tmp_path, point_format=0)  # no gps_time
    assert execute_job(settings, store, job.id) is JobStatus.failed
    failed = store.get_job(job.id)
    assert "gps_time" in failed.message and failed.finished
    assert not layout.result_path(settings, job.id, False).exists()


def test_job_whose_worker_died_twice_fails(service, store, settings, tmp_path) -> None:
    alice, _ = store.add_user("alice")
    job, _ = submit(service, alice, tmp_path)
    store.transition(job.id, JobStatus.running, worker_pid=1)  # two deliveries that died
    store.transition(job.id, JobStatus.running, worker_pid=2)
    assert execute_job(settings, store, job.id) is JobStatus.failed
    assert "died 2 times" in store.get_job(job.id).message


def test_dismissed_before_running_is_skipped(service, store, settings, tmp_path) -> None:
    alice, _ = store.add_user("alice")
    job, _ = submit(service, alice, tmp_path)
    service.dismiss(alice, job.id)
    assert execute_job(settings, store, job.id) is None
    assert store.get_job(job.id).status is JobStatus.dismissed
    assert not layout.job_dir(settings, job.id).exists()


def test_retention_deletes_old_results_only(service, store, settings, tmp_path) -> None:
    alice, _ = store.add_user("alice")
    old, _ = submit(service, alice, tmp_path, "old.las")
    new, _ = submit(service, alice, tmp_path, "new.las")
    active, _ = submit(service, alice, tmp_path, "active.las")
    for job in (old, new):
        execute_job(settings, store, job.id)
    upload = service.store_upload(alice, _part(tmp_path, settings), "up.las")
    later = datetime.now(UTC) + timedelta(days=settings.retention_days, hours=1)
    # pretend "new" finished just now relative to `later`
    stamp = later.isoformat(timespec="milliseconds").replace("+00:00", "Z")
    import sqlite3

    with sqlite3.connect(settings.db_path) as db:
        db.execute("UPDATE jobs SET finished = ? WHERE id = ?", (stamp, new.id))
    removed = service.cleanup(now=later)
    assert removed == 2  # the old job and the upload
    assert store.get_job(old.id) is None and not layout.job_dir(settings, old.id).exists()
    assert store.get_job(new.id) is not None and layout.job_dir(settings, new.id).exists()
    assert store.get_job(active.id).status is JobStatus.accepted
    assert not Path(upload.path).exists()


def _part(tmp_path: Path, settings: Settings) -> Path:
    part = settings.uploads_dir / "incoming" / "x.part"
    part.parent.mkdir(parents=True, exist_ok=True)
    write_cloud(tmp_path / "up.las", n=500)
    os.replace(tmp_path / "up.las", part)
    return part


def run_cli(tmp_path: Path, *args: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, DATA_DIR=str(tmp_path / "data"))
    return subprocess.run([str(Path(sys.executable).parent / "lidar-outliers"), *args],
                          env=env, cwd=ROOT, capture_output=True, text=True, timeout=60)


def test_users_command(tmp_path: Path) -> None:
    added = run_cli(tmp_path, "users", "add", "alice")
    assert added.returncode == 0, added.stderr
    key = added.stdout.strip().splitlines()[-1]
    assert key.startswith("lo_") and " " not in key
    store = Store(tmp_path / "data" / "service.sqlite3")
    assert store.user_for_key(key).name == "alice"
    assert run_cli(tmp_path, "users", "add", "alice").returncode == 1
    listed = run_cli(tmp_path, "users", "list").stdout
    assert "alice" in listed and key not in listed
    assert run_cli(tmp_path, "users", "revoke", "alice").returncode == 0
    assert store.user_for_key(key) is None
    gone = run_cli(tmp_path, "users", "revoke", "alice")
    assert gone.returncode == 1 and gone.stderr.count("\n") == 1
    assert "revoked" in run_cli(tmp_path, "users", "list").stdout


def test_settings_from_environment(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv("DATA_DIR", str(tmp_path))
    monkeypatch.setenv("MAX_UPLOAD_BYTES", "1000")
    monkeypatch.setenv("REDIS_URL", "redis://example:6380/2")
    s = Settings()
    assert s.data_dir == tmp_path and s.max_upload_bytes == 1000
    assert s.redis_url == "redis://example:6380/2"
    assert s.db_path == tmp_path / "service.sqlite3"
    assert s.visibility_timeout > s.task_time_limit > s.soft_time_limit
    monkeypatch.setenv("VISIBILITY_TIMEOUT", "10")
    with pytest.raises(ValueError, match="VISIBILITY_TIMEOUT"):
        Settings(task_time_limit=20)


def test_prod_needs_explicit_redis_and_data_dir(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="DATA_DIR, REDIS_URL"):
        Settings(environment="prod")
    Settings(environment="prod", data_dir=tmp_path, redis_url="redis://r:6379/0")


def test_storage_quota_bounds_uploads(store: Store, tmp_path: Path) -> None:
    settings = Settings(data_dir=tmp_path / "data", max_stored_bytes_per_user=10_000,
                        max_upload_bytes=8_000)
    service = JobService(settings, store, enqueue=lambda job_id, p: None)
    alice, _ = store.add_user("alice")
    assert service.upload_limit(alice) == (8_000, False)
    part = _part(tmp_path, settings)
    upload = service.store_upload(alice, part, "up.las")
    left, quota = service.upload_limit(alice)
    assert quota and left == max(0, 10_000 - upload.bytes)
