"""Service logic without HTTP: submission, the worker's job run, retention. Real LAS files,
in both deployments: SQLite with files under DATA_DIR, and PostgreSQL with S3 storage."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from collections.abc import Iterator
from datetime import UTC, datetime, timedelta
from pathlib import Path

import laspy
import numpy as np
import pytest
import sqlalchemy as sa

from lidar_outliers.jobs import layout
from lidar_outliers.jobs.execute import execute_job
from lidar_outliers.jobs.schema import jobs, uploads
from lidar_outliers.jobs.settings import Settings
from lidar_outliers.jobs.storage import Storage, open_storage
from lidar_outliers.jobs.store import JobStatus, Store
from service.jobs import JobService
from service.problems import Problem
from tests.backends import clear
from tests.lasfiles import write_cloud, write_las

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(params=["sqlite+local", "postgresql+s3"])
def deployment(request: pytest.FixtureRequest, tmp_path: Path) -> dict[str, str]:
    """The settings that choose the database and the storage."""
    if request.param == "sqlite+local":
        return {}
    url = request.getfixturevalue("postgres_url")
    clear(url)
    moto = request.getfixturevalue("moto")
    return {"database_url": url, "storage_url": f"s3://{moto.new_bucket()}/service",
            "s3_endpoint_url": moto.url}


@pytest.fixture
def settings(tmp_path: Path, deployment: dict[str, str]) -> Settings:
    return Settings(data_dir=tmp_path / "data", max_active_jobs_per_user=3, **deployment)


@pytest.fixture
def store(settings: Settings) -> Iterator[Store]:
    store = Store(settings.database_url)
    yield store
    store.close()


@pytest.fixture
def storage(settings: Settings) -> Storage:
    return open_storage(settings)


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
    return service.submit(user, "temporal", params, path, name), spikes


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


def test_worker_run_writes_result_and_statistics(service, store, storage, settings,
                                                 tmp_path) -> None:
    alice, _ = store.add_user("alice")
    job, spikes = submit(service, alice, tmp_path)
    assert not (tmp_path / "scan.las").exists()  # moved into the storage
    assert execute_job(settings, store, job.id) is JobStatus.successful
    done = store.get_job(job.id)
    assert done.status is JobStatus.successful and done.progress == 100
    assert done.stored_bytes == storage.prefix_bytes(layout.job_prefix(job.id))
    storage.get_file(layout.result_key(job.id, False), tmp_path / "result.las")
    las = laspy.read(tmp_path / "result.las")
    assert set(spikes) <= set(np.flatnonzero(np.asarray(las.outlier_flags)))
    stats = json.loads(storage.read_bytes(layout.statistics_key(job.id)))
    assert "temporal" in json.dumps(stats)
    assert stats["input"]["name"] == "scan.las"
    assert list(settings.scratch_dir.iterdir()) == []  # the worker's copies are gone
    # a late re-delivery of a finished job does nothing
    assert execute_job(settings, store, job.id) is None

    # downloads made on first request are stored beside the result
    key, info, laz = service.cloud(alice, job.id, "inliers", True)
    assert key == layout.derived_key(job.id, "inliers", True) and laz
    assert storage.info(key) == info and info.size > 0
    assert service.cloud(alice, job.id, "inliers", True)[1] == info  # made once
    key, info = service.preview(alice, job.id)
    assert storage.read_bytes(key).startswith(b"\x89PNG")
    assert list(settings.scratch_dir.iterdir()) == []
    service.dismiss(alice, job.id)
    assert storage.prefix_bytes(layout.job_prefix(job.id)) == 0


def test_a_download_made_while_its_job_is_dismissed_leaves_no_file(service, store, storage,
                                                                     settings, tmp_path) -> None:
    # dismissal deletes the job's files; a derived file put after that must go too
    alice, _ = store.add_user("alice")
    job, _ = submit(service, alice, tmp_path)
    assert execute_job(settings, store, job.id) is JobStatus.successful
    key = layout.derived_key(job.id, "inliers", True)

    def make_while_dismissed(result: Path, out: Path) -> None:
        service.dismiss(alice, job.id)  # the user's DELETE lands mid-way
        out.write_bytes(result.read_bytes())

    with pytest.raises(Problem) as gone:
        service._derive(store.get_job(job.id), key, make_while_dismissed)
    assert gone.value.status == 404
    assert storage.prefix_bytes(layout.job_prefix(job.id)) == 0


def test_worker_failure_is_recorded_with_its_message(service, store, storage, settings,
                                                     tmp_path):
    alice, _ = store.add_user("alice")
    # every time stamp NaN: the header allows it, the temporal detector cannot run
    path = write_las(tmp_path / "untimed.las", np.random.default_rng(1).random((500, 3)),
                     gps_time=np.full(500, np.nan), point_format=1)
    params, _ = service.parse_inputs("temporal", {"sigma": 0.01})
    job = service.submit(alice, "temporal", params, path, "untimed.las")
    assert execute_job(settings, store, job.id) is JobStatus.failed
    failed = store.get_job(job.id)
    assert "gps_time is all NaN" in failed.message and failed.finished
    assert not storage.exists(layout.result_key(job.id, False))
    assert failed.stored_bytes == storage.size(layout.input_key(job.id, False))


def test_job_whose_worker_died_twice_fails(service, store, settings, tmp_path) -> None:
    alice, _ = store.add_user("alice")
    job, _ = submit(service, alice, tmp_path)
    store.transition(job.id, JobStatus.running, worker_pid=1)  # two deliveries that died
    store.transition(job.id, JobStatus.running, worker_pid=2)
    assert execute_job(settings, store, job.id) is JobStatus.failed
    assert "died 2 times" in store.get_job(job.id).message


def test_dismissed_before_running_is_skipped(service, store, storage, settings,
                                             tmp_path) -> None:
    alice, _ = store.add_user("alice")
    job, _ = submit(service, alice, tmp_path)
    service.dismiss(alice, job.id)
    assert execute_job(settings, store, job.id) is None
    assert store.get_job(job.id).status is JobStatus.dismissed
    assert storage.prefix_bytes(layout.job_prefix(job.id)) == 0


def test_retention_deletes_old_results_only(service, store, storage, settings,
                                            tmp_path) -> None:
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
    with store.engine.begin() as db:
        db.execute(sa.update(jobs).where(jobs.c.id == new.id).values(finished=stamp))
    removed = service.cleanup(now=later)
    assert removed == 2  # the old job and the upload
    assert store.get_job(old.id) is None
    assert storage.prefix_bytes(layout.job_prefix(old.id)) == 0
    assert store.get_job(new.id) is not None
    assert storage.exists(layout.result_key(new.id, False))
    assert store.get_job(active.id).status is JobStatus.accepted
    assert not storage.exists(upload.key)


def test_retention_removes_expired_resumable_uploads(service, store, settings) -> None:
    """An unfinished tus upload past its expiry goes with its partial file, and the bytes it
    reserved are free again; one still in time stays; stray partial files older than any
    upload may live go too."""
    alice, _ = store.add_user("alice")
    now = datetime.now(UTC)

    def stamp(moment: datetime) -> str:
        return moment.isoformat(timespec="milliseconds").replace("+00:00", "Z")

    stale = store.add_resumable(alice.id, "a.las", "cloud", 1000, stamp(now - timedelta(hours=1)),
                                "host", max_stored_bytes=settings.max_stored_bytes_per_user)
    fresh = store.add_resumable(alice.id, "b.las", "cloud", 500, stamp(now + timedelta(hours=1)),
                                "host")
    folder = settings.resumable_dir
    folder.mkdir(parents=True)
    for upload in (stale, fresh):
        (folder / f"{upload.id}.part").write_bytes(b"LASF")
    stray = folder / "0123.part"
    stray.write_bytes(b"LASF")
    old = (now - timedelta(hours=settings.resumable_expiry_hours + 2)).timestamp()
    os.utime(stray, (old, old))
    assert store.stored_bytes(alice.id) == 1500
    assert service.cleanup(now=now) == 1
    assert store.get_resumable(stale.id, alice.id) is None
    assert store.get_resumable(fresh.id, alice.id) is not None
    assert sorted(p.name for p in folder.iterdir()) == [f"{fresh.id}.part"]
    assert store.stored_bytes(alice.id) == 500


def _part(tmp_path: Path, settings: Settings) -> Path:
    part = settings.incoming_dir / "x.part"
    part.parent.mkdir(parents=True, exist_ok=True)
    write_cloud(tmp_path / "up.las", n=500)
    os.replace(tmp_path / "up.las", part)
    return part


def run_cli(tmp_path: Path, *args: str, **settings: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, DATA_DIR=str(tmp_path / "data"), **settings)
    return subprocess.run([sys.executable, "-m", "lidar_outliers", *args],  # this checkout
                          env=env, cwd=ROOT, capture_output=True, text=True, timeout=60)


def test_users_command(tmp_path: Path) -> None:
    added = run_cli(tmp_path, "users", "add", "alice")
    assert added.returncode == 0, added.stderr
    key = added.stdout.strip().splitlines()[-1]
    assert key.startswith("lo_") and " " not in key
    assert "alice" in added.stdout and "service.sqlite3" in added.stdout
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


def test_users_command_migrates_a_new_postgres_database(postgres, tmp_path: Path) -> None:
    from lidar_outliers.jobs import database

    with postgres.database() as url:
        added = run_cli(tmp_path, "users", "add", "alice", DATABASE_URL=url)
        assert added.returncode == 0, added.stderr
        assert url.rsplit("/", 1)[1] in added.stdout
        store = Store(url)
        try:
            assert database.current(store.engine) == database.head()
            assert store.user_for_key(added.stdout.strip().splitlines()[-1]).name == "alice"
        finally:
            store.close()
    wrong = run_cli(tmp_path, "users", "list",
                    DATABASE_URL="postgresql://nobody:secret@127.0.0.1:1/none")
    assert wrong.returncode == 1 and wrong.stderr.count("\n") == 1
    assert "cannot be used" in wrong.stderr and "secret" not in wrong.stderr


def test_settings_from_environment(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv("DATA_DIR", str(tmp_path))
    monkeypatch.setenv("MAX_UPLOAD_BYTES", "1000")
    monkeypatch.setenv("REDIS_URL", "redis://example:6380/2")
    s = Settings()
    assert s.data_dir == tmp_path and s.max_upload_bytes == 1000
    assert s.redis_url == "redis://example:6380/2"
    assert s.db_path == tmp_path / "service.sqlite3"
    assert s.database_url == f"sqlite:///{tmp_path / 'service.sqlite3'}"
    assert s.storage_url == "" and s.scratch_dir == tmp_path / "scratch"
    assert s.visibility_timeout > s.task_time_limit > s.soft_time_limit
    monkeypatch.setenv("VISIBILITY_TIMEOUT", "10")
    with pytest.raises(ValueError, match="VISIBILITY_TIMEOUT"):
        Settings(task_time_limit=20)


def test_prod_needs_explicit_redis_and_data_dir(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="DATA_DIR, REDIS_URL"):
        Settings(environment="prod")
    Settings(environment="prod", data_dir=tmp_path, redis_url="redis://r:6379/0")


def test_storage_quota_bounds_uploads_and_jobs(store: Store, tmp_path: Path,
                                               deployment: dict[str, str]) -> None:
    settings = Settings(data_dir=tmp_path / "data", max_stored_bytes_per_user=60_000,
                        max_upload_bytes=50_000, **deployment)
    service = JobService(settings, store, enqueue=lambda job_id, p: None)
    alice, _ = store.add_user("alice")
    assert service.upload_limit(alice) == (50_000, False)
    part = _part(tmp_path, settings)
    upload = service.store_upload(alice, part, "up.las")
    assert not part.exists() and upload.facts["points"] == 500
    left, quota = service.upload_limit(alice)
    assert quota and left == max(0, 60_000 - upload.bytes)
    params, _ = service.parse_inputs("temporal", {})
    while store.stored_bytes(alice.id) + upload.bytes <= 60_000:
        service.submit(alice, "temporal", params, upload)
    with pytest.raises(Problem) as refused:  # the job's copy of the upload does not fit
        service.submit(alice, "temporal", params, upload)
    assert refused.value.status == 413 and refused.value.slug == "storage-quota-exceeded"
    assert store.stored_bytes(alice.id) <= 60_000


def test_a_refused_or_unqueued_job_keeps_nothing(store: Store, storage: Storage,
                                                 settings: Settings, tmp_path: Path) -> None:
    alice, _ = store.add_user("alice")

    def broken_queue(job_id: str, priority: int) -> None:
        raise ConnectionError("Redis is down")

    service = JobService(settings, store, enqueue=broken_queue, storage=storage)
    with pytest.raises(Problem) as refused:
        submit(service, alice, tmp_path)
    assert refused.value.status == 503 and "Redis is down" in refused.value.detail
    [job], _ = store.list_jobs(alice.id, 10, 0)
    assert job.status is JobStatus.failed and "could not queue" in job.message
    assert job.stored_bytes == 0 and store.count_active(alice.id) == 0
    assert storage.prefix_bytes(layout.job_prefix(job.id)) == 0
    assert not (tmp_path / "scan.las").exists()
    # a file that is not LAS: 415, no record, the part removed
    bad = tmp_path / "bad.las"
    bad.write_bytes(b"x,y,z\n" * 100)
    params, _ = service.parse_inputs("temporal", {})
    with pytest.raises(Problem) as unsupported:
        service.submit(alice, "temporal", params, bad)
    assert unsupported.value.status == 415 and not bad.exists()
    assert store.list_jobs(alice.id, 10, 0)[1] == 1


def test_jobs_from_a_stored_upload_and_trajectory(store: Store, storage: Storage,
                                                  settings: Settings, tmp_path: Path) -> None:
    """JSON submissions name stored uploads: copied inside the storage, the upload stays; an
    upload recorded without facts is read from the storage once."""
    from lidar_outliers.tools.simulator import simulate, write_simulation

    las = write_simulation(simulate("A", 3, 0.01), tmp_path / "sim")
    service = JobService(settings, store, enqueue=lambda job_id, p: None, storage=storage)
    alice, _ = store.add_user("alice")
    incoming = settings.incoming_dir
    incoming.mkdir(parents=True, exist_ok=True)
    cloud = service.store_upload(alice, Path(shutil.copy(las, incoming / "a.part")), "a.las")
    traj = service.store_upload(alice, Path(shutil.copy(las.with_suffix(".trajectory.txt"),
                                                        incoming / "t.part")),
                                "drive.txt", "trajectory")
    assert traj.key.endswith(".txt") and traj.facts["samples"] > 10
    params, _ = service.parse_inputs("pipeline", {})
    job = service.submit(alice, "pipeline", params, cloud, trajectory=traj)
    assert job.facts["name"] == "a.las" and job.facts["trajectory"]["name"] == "drive.txt"
    assert storage.exists(cloud.key) and storage.exists(layout.trajectory_key(job.id))
    assert job.stored_bytes == cloud.bytes + traj.bytes
    assert execute_job(settings, store, job.id, storage=storage) is JobStatus.successful
    stats = json.loads(storage.read_bytes(layout.statistics_key(job.id)))
    assert stats["trajectory"]["name"] == "drive.txt"

    with store.engine.begin() as db:  # an upload recorded before facts were kept
        db.execute(sa.update(uploads).where(uploads.c.id == cloud.id).values(facts=None))
    again = service.submit(alice, "pipeline", params, service.find_upload(alice, cloud.id))
    assert again.facts["points"] == job.facts["points"]
    with pytest.raises(Problem) as swapped:  # each upload is of its own kind
        service.submit(alice, "pipeline", params, traj)
    assert swapped.value.status == 415 and "drive.txt" in swapped.value.detail
    with pytest.raises(Problem) as swapped:
        service.submit(alice, "pipeline", params, cloud, trajectory=cloud)
    assert swapped.value.status == 422
    assert list(settings.scratch_dir.iterdir()) == []

    # the upload deleted while a job is made from it: 422, and no job is left behind
    jobs_before = store.list_jobs(alice.id, 100, 0)[1]
    storage.delete(cloud.key)
    with pytest.raises(Problem) as gone:
        service.submit(alice, "pipeline", params, cloud)
    assert gone.value.status == 422 and "upload the file again" in gone.value.detail
    assert store.list_jobs(alice.id, 100, 0)[1] == jobs_before
    with store.engine.begin() as db:  # without recorded facts the file is read first
        db.execute(sa.update(uploads).where(uploads.c.id == cloud.id).values(facts=None))
    with pytest.raises(Problem) as gone:
        service.submit(alice, "pipeline", params, service.find_upload(alice, cloud.id))
    assert gone.value.status == 422 and store.list_jobs(alice.id, 100, 0)[1] == jobs_before
