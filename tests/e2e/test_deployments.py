"""The whole stack (uvicorn, a real Celery worker, Redis) in both deployments: the embedded one
(SQLite, files under DATA_DIR) and the one for several hosts (PostgreSQL, S3 storage on a moto
server). Submit, run, download with HTTP range requests; limits under concurrent submissions.
"""

from __future__ import annotations

import json
import re
import threading
from collections import Counter
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import laspy
import pytest
import sqlalchemy as sa

from lidar_outliers.jobs import database
from tests.e2e.stack import RedisServer, Stack, running_stack, wait_for, wait_job
from tests.lasfiles import write_cloud

DEPLOYMENTS = ["sqlite+local", "postgresql+s3"]


@pytest.fixture(scope="module")
def deployments(request: pytest.FixtureRequest) -> Iterator[dict]:
    """Settings for either deployment; PostgreSQL databases made here are dropped at the end."""
    made: list[str] = []

    def settings(name: str) -> dict[str, str]:
        if name == "sqlite+local":
            return {}
        postgres = request.getfixturevalue("postgres")
        moto = request.getfixturevalue("moto")
        made.append(postgres.create())
        return {"database_url": made[-1], "storage_url": f"s3://{moto.new_bucket()}/service",
                "s3_endpoint_url": moto.url}

    yield {"settings": settings}
    if made:
        postgres = request.getfixturevalue("postgres")
        for url in made:
            postgres.drop(url)


@pytest.fixture(scope="module", params=DEPLOYMENTS)
def stack(request: pytest.FixtureRequest, deployments: dict, redis_server: RedisServer,
          tmp_path_factory: pytest.TempPathFactory, compiled_detectors: None) -> Iterator[Stack]:
    settings = deployments["settings"](request.param)
    with running_stack(tmp_path_factory.mktemp("data"), redis_server.new_url(),
                       max_active_jobs_per_user=8, **settings) as s:
        s.deployment = request.param  # type: ignore[attr-defined]
        s.settings = settings  # type: ignore[attr-defined]
        yield s


@pytest.fixture(scope="module")
def las_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("in") / "scan.las"
    write_cloud(path, n=3000, seed=11)
    return path


def parse_multipart(answer: httpx.Response) -> list[tuple[str, bytes]]:
    """(Content-Range, body) of each part of a multipart/byteranges answer."""
    boundary = answer.headers["content-type"].split("boundary=")[1].encode()
    parts = []
    for chunk in answer.content.split(b"--" + boundary)[1:]:
        if chunk.startswith(b"--"):
            break
        head, _, body = chunk.lstrip(b"\r\n").partition(b"\r\n\r\n")
        content_range = re.search(rb"Content-Range: (.*)", head).group(1).decode().strip()
        parts.append((content_range, body.removesuffix(b"\r\n")))
    return parts


def test_submit_run_and_download_with_ranges(stack: Stack, las_file: Path,
                                             tmp_path: Path) -> None:
    key = stack.add_user("alice")
    with stack.client(key) as client:
        health = client.get("/health").json()
        assert health["database"] == health["storage"] == "ok", health
        answer = client.post("/processes/temporal/execution",
                             files={"file": ("scan.las", las_file.read_bytes())},
                             data={"inputs": json.dumps({"sigma": 0.01})})
        assert answer.status_code == 201, answer.text
        job = answer.json()["jobID"]
        done = wait_job(client, job, ("successful", "failed"))
        assert done["status"] == "successful", done["message"]
        url = f"/jobs/{job}/results/cloud"

        full = client.get(url)
        assert full.status_code == 200 and full.headers["accept-ranges"] == "bytes"
        size = len(full.content)
        assert int(full.headers["content-length"]) == size
        etag = full.headers["etag"]
        (tmp_path / "out.las").write_bytes(full.content)
        assert len(laspy.read(tmp_path / "out.las").points) == 3000

        first = client.get(url, headers={"Range": "bytes=0-99"})
        assert first.status_code == 206
        assert first.headers["content-range"] == f"bytes 0-99/{size}"
        assert first.content == full.content[:100] and first.content.startswith(b"LASF")
        assert client.get(url, headers={"Range": "bytes=-10"}).content == full.content[-10:]
        # a download resumed in pieces is the same file
        pieces = [client.get(url, headers={"Range": f"bytes={a}-{b}"}).content
                  for a, b in ((0, 999), (1000, size // 2), (size // 2 + 1, size + 50))]
        assert b"".join(pieces) == full.content

        several = client.get(url, headers={"Range": "bytes=0-9, 5-19, 100-109"})
        assert several.status_code == 206
        assert several.headers["content-type"].startswith("multipart/byteranges")
        assert parse_multipart(several) == [(f"bytes 0-19/{size}", full.content[:20]),
                                            (f"bytes 100-109/{size}", full.content[100:110])]
        assert int(several.headers["content-length"]) == len(several.content)

        for bad in (f"bytes={size}-", "bytes=abc", "bytes=9-3", "bytes=-0"):
            refused = client.get(url, headers={"Range": bad})
            assert refused.status_code == 416, (bad, refused.text)
            assert refused.headers["content-range"] == f"bytes */{size}"
            assert refused.headers["content-type"] == "application/problem+json"
        assert client.get(url, headers={"Range": "items=0-1"}).status_code == 200
        assert client.get(url, headers={"Range": "bytes=0-9", "If-Range": etag}).status_code \
            == 206
        stale = client.get(url, headers={"Range": "bytes=0-9", "If-Range": '"other"'})
        assert stale.status_code == 200 and len(stale.content) == size
        head = client.head(url, headers={"Range": "bytes=10-19"})
        assert head.status_code == 206 and head.headers["content-length"] == "10"
        assert head.content == b""

        stats = client.get(f"/jobs/{job}/results/statistics", headers={"Range": "bytes=0-0"})
        assert stats.status_code == 206 and stats.content == b"{"
        # a derived download, made on first request, honours ranges too
        laz = client.get(url, params={"format": "laz"})
        assert laz.status_code == 200 and laz.headers["content-type"] == "application/vnd.laszip"
        tail = client.get(url, params={"format": "laz"}, headers={"Range": "bytes=-100"})
        assert tail.status_code == 206 and tail.content == laz.content[-100:]
        preview = client.get(f"/jobs/{job}/results/preview", headers={"Range": "bytes=0-3"})
        assert preview.status_code == 206 and preview.content == b"\x89PNG"

    if stack.deployment == "postgresql+s3":
        _check_nothing_shared_on_disk(stack, job)


def _check_nothing_shared_on_disk(stack: Stack, job: str) -> None:
    """Records in PostgreSQL, files in S3: the API's and the worker's DATA_DIR keep no job."""
    import boto3

    settings = stack.settings  # type: ignore[attr-defined]
    bucket = settings["storage_url"].split("/")[2]
    s3 = boto3.client("s3", endpoint_url=settings["s3_endpoint_url"])
    keys = {o["Key"] for o in s3.list_objects_v2(Bucket=bucket)["Contents"]}
    assert {f"service/jobs/{job}/{name}" for name in (
        "input.las", "result.las", "statistics.json", "cloud-all.laz", "preview.png")} <= keys
    assert not (stack.data_dir / "jobs").exists()
    assert not (stack.data_dir / "service.sqlite3").exists()
    assert list((stack.data_dir / "scratch").glob("*")) == []
    engine = sa.create_engine(sa.make_url(settings["database_url"])
                              .set(drivername="postgresql+psycopg"), poolclass=sa.NullPool)
    with engine.connect() as db:
        assert db.execute(sa.text("SELECT status FROM jobs WHERE id = :id"),
                          {"id": job}).scalar() == "successful"
    engine.dispose()


def test_upload_then_job_by_href(stack: Stack, las_file: Path) -> None:
    key = stack.add_user("bob")
    with stack.client(key) as client:
        up = client.post("/uploads", params={"name": "scan.las"}, content=las_file.read_bytes())
        assert up.status_code == 201, up.text
        answer = client.post("/processes/temporal/execution",
                             json={"inputs": {"cloud": {"href": up.json()["href"]}}})
        assert answer.status_code == 201, answer.text
        done = wait_job(client, answer.json()["jobID"], ("successful", "failed"))
        assert done["status"] == "successful", done["message"]
        assert done["input_file"]["name"] == "scan.las"


def test_resumable_upload_cut_at_half_then_job_by_href(stack: Stack, las_file: Path) -> None:
    """tus: half the file, a PATCH cut by a closed connection, the rest from the server's
    offset; the finished upload (in the deployment's storage) runs as a job."""
    import base64
    import socket

    key = stack.add_user("tess")
    data = las_file.read_bytes()
    half = len(data) // 2
    tus = {"Tus-Resumable": "1.0.0"}
    octets = tus | {"Content-Type": "application/offset+octet-stream"}
    with stack.client(key) as client:
        created = client.post("/uploads/tus", headers=tus | {
            "Upload-Length": str(len(data)),
            "Upload-Metadata": "filename " + base64.b64encode(b"scan.las").decode()})
        assert created.status_code == 201, created.text
        location = created.headers["location"]
        with socket.create_connection(("127.0.0.1", stack.port), timeout=10) as sock:
            sock.sendall(f"PATCH {location} HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer "
                         f"{key}\r\nTus-Resumable: 1.0.0\r\nContent-Type: application/"
                         f"offset+octet-stream\r\nUpload-Offset: 0\r\nContent-Length: "
                         f"{len(data)}\r\n\r\n".encode() + data[:half])
            # closed once the API has written what it received (bytes still in its buffers
            # when the connection drops are lost, as on any link)
            part = stack.data_dir / "uploads" / "resumable" / f"{location.rsplit('/')[-1]}.part"
            wait_for(lambda: part.stat().st_size == half, 30, "the first half on disk")

        def offset() -> int:
            return int(client.head(location, headers=tus).headers["upload-offset"])

        wait_for(lambda: offset() == half, 30, "the offset after the cut")
        done = client.patch(location, content=data[half:],
                            headers=octets | {"Upload-Offset": str(half)})
        assert done.status_code == 204, done.text
        answer = client.post("/processes/temporal/execution",
                             json={"inputs": {"cloud": {"href": done.headers["upload-href"]}}})
        assert answer.status_code == 201, answer.text
        job = wait_job(client, answer.json()["jobID"], ("successful", "failed"))
        assert job["status"] == "successful", job["message"]
        assert job["input_file"]["name"] == "scan.las"
        assert job["input_file"]["bytes"] == len(data)


@pytest.fixture(scope="module", params=DEPLOYMENTS)
def queue_only(request: pytest.FixtureRequest, deployments: dict, redis_server: RedisServer,
               tmp_path_factory: pytest.TempPathFactory) -> Iterator[Stack]:
    """No worker: every accepted job stays queued, so it counts against the limit."""
    settings = deployments["settings"](request.param)
    with running_stack(tmp_path_factory.mktemp("queue"), redis_server.new_url(), workers=0,
                       max_active_jobs_per_user=4, **settings) as s:
        yield s


def test_concurrent_submissions_respect_the_limit(queue_only: Stack, tmp_path: Path) -> None:
    """30 submissions at once over HTTP, 10 from each of 3 users, limit 4: 4 accepted each,
    the rest 429; the records agree."""
    path = tmp_path / "small.las"
    write_cloud(path, n=500, seed=12)
    data = path.read_bytes()
    keys = {name: queue_only.add_user(name) for name in ("ann", "ben", "cat")}
    barrier = threading.Barrier(30)

    def submit(name: str) -> tuple[str, int]:
        with queue_only.client(keys[name]) as client:
            barrier.wait()
            answer = client.post("/processes/temporal/execution",
                                 files={"file": ("small.las", data)})
            return name, answer.status_code

    with ThreadPoolExecutor(30) as pool:
        outcomes = list(pool.map(submit, [n for n in keys for _ in range(10)]))
    assert {code for _, code in outcomes} == {201, 429}
    accepted = Counter(name for name, code in outcomes if code == 201)
    assert accepted == dict.fromkeys(keys, 4), accepted
    for key in keys.values():
        with queue_only.client(key) as client:
            listing = client.get("/jobs").json()
        assert listing["numberMatched"] == 4  # refused submissions left no record
        assert {j["status"] for j in listing["jobs"]} == {"accepted"}
    assert list((queue_only.data_dir / "uploads" / "incoming").glob("*")) == []


def test_workers_alone_migrate_a_new_database(postgres, redis_server: RedisServer,
                                              tmp_path: Path) -> None:
    """Two workers start on an empty PostgreSQL database before any API: the schema is made
    once, under the lock, and both serve."""
    with postgres.database() as url:
        stack = Stack(tmp_path / "data", redis_server.new_url(), database_url=url)
        try:
            stack.start_worker()
            stack.start_worker()
            stack.wait_workers_ready()
            engine = sa.create_engine(database.normalise_url(url), poolclass=sa.NullPool)
            assert database.current(engine) == database.head()
            engine.dispose()
        finally:
            stack.stop()
