"""Resumable uploads (tus 1.0.0) over real HTTP against the real stack (uvicorn, Redis, a
worker): an upload cut at half continues from the server's offset, checksums and offsets are
enforced, uploads are private, a finished one runs as a job like a plain upload, the client
resumes after a dropped connection, and the documented curl loop (docs/service.md) works."""

from __future__ import annotations

import base64
import hashlib
import re
import socket
import subprocess
from collections.abc import Iterator
from pathlib import Path

import httpx
import laspy
import numpy as np
import pytest
import sqlalchemy as sa

from lidar_outliers.client import Client, ServiceError
from tests.e2e.stack import RedisServer, Stack, running_stack, wait_for, wait_job
from tests.lasfiles import write_cloud

ROOT = Path(__file__).resolve().parents[2]
TUS = {"Tus-Resumable": "1.0.0"}
OCTETS = {"Content-Type": "application/offset+octet-stream"}
MAX_UPLOAD = 16_000_000
QUOTA = 40_000_000


@pytest.fixture(scope="module")
def stack(redis_server: RedisServer, tmp_path_factory: pytest.TempPathFactory,
          compiled_detectors: None) -> Iterator[Stack]:
    with running_stack(tmp_path_factory.mktemp("data"), redis_server.new_url(),
                       max_active_jobs_per_user=8, max_upload_bytes=MAX_UPLOAD,
                       max_stored_bytes_per_user=QUOTA) as s:
        yield s


@pytest.fixture(scope="module")
def key(stack: Stack) -> str:
    return stack.add_user("field-crew")


@pytest.fixture(scope="module")
def las_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("in") / "scan.las"
    write_cloud(path, n=6000, seed=21)
    return path


def create(client: httpx.Client, size: int, name: str = "scan.las") -> str:
    answer = client.post("/uploads/tus", headers=TUS | {
        "Upload-Length": str(size),
        "Upload-Metadata": f"filename {base64.b64encode(name.encode()).decode()}"})
    assert answer.status_code == 201, answer.text
    assert answer.headers["tus-resumable"] == "1.0.0" and "upload-expires" in answer.headers
    return answer.headers["location"]


def offset_of(client: httpx.Client, location: str) -> int:
    answer = client.head(location, headers=TUS)
    assert answer.status_code == 200, answer.headers
    return int(answer.headers["upload-offset"])


def patch(client: httpx.Client, location: str, offset: int, body: bytes,
          checksum: str | None = None) -> httpx.Response:
    headers = TUS | OCTETS | {"Upload-Offset": str(offset)}
    if checksum:
        headers["Upload-Checksum"] = checksum
    return client.patch(location, content=body, headers=headers)


def sha(algorithm: str, data: bytes) -> str:
    return f"{algorithm} {base64.b64encode(hashlib.new(algorithm, data).digest()).decode()}"


def stored_object(stack: Stack, upload_id: str) -> bytes:
    """The finished upload's bytes in the storage (files under DATA_DIR here)."""
    found = list((stack.data_dir / "uploads").glob(f"*/{upload_id}.la[sz]"))
    assert len(found) == 1, found
    return found[0].read_bytes()


def cut_patch(stack: Stack, key: str, location: str, offset: int, body: bytes,
              declared: int) -> None:
    """A PATCH announcing ``declared`` bytes whose connection closes after ``body``."""
    head = (f"PATCH {location} HTTP/1.1\r\nHost: 127.0.0.1\r\nAuthorization: Bearer {key}\r\n"
            f"Tus-Resumable: 1.0.0\r\nContent-Type: application/offset+octet-stream\r\n"
            f"Upload-Offset: {offset}\r\nContent-Length: {declared}\r\n\r\n").encode()
    part = stack.data_dir / "uploads" / "resumable" / f"{location.rsplit('/', 1)[1]}.part"
    with socket.create_connection(("127.0.0.1", stack.port), timeout=10) as sock:
        sock.sendall(head + body)
        # closed once the API has written what it received (bytes still in its buffers when
        # the connection drops are lost, as on any link)
        wait_for(lambda: part.stat().st_size == offset + len(body), 30, "the bytes on disk")


def test_options_advertise_the_protocol(stack: Stack) -> None:
    answer = httpx.options(f"{stack.url}/uploads/tus")
    assert answer.status_code == 204
    assert answer.headers["tus-version"] == "1.0.0"
    assert set(answer.headers["tus-extension"].split(",")) == {
        "creation", "checksum", "termination", "expiration"}
    assert int(answer.headers["tus-max-size"]) == MAX_UPLOAD
    assert {"sha1", "sha256"} <= set(answer.headers["tus-checksum-algorithm"].split(","))


def test_cut_at_half_resumes_from_the_server_offset(stack: Stack, key: str,
                                                    las_file: Path) -> None:
    data = las_file.read_bytes()
    half = len(data) // 2
    with stack.client(key) as client:
        location = create(client, len(data))
        assert offset_of(client, location) == 0
        cut_patch(stack, key, location, 0, data[:half], declared=len(data))
        # the server keeps what arrived before the cut (no checksum to verify it against)
        wait_for(lambda: offset_of(client, location) == half, 30, "the offset of the cut PATCH")
        answer = patch(client, location, half, data[half:])  # only the second half goes again
        assert answer.status_code == 204, answer.text
        assert int(answer.headers["upload-offset"]) == len(data)
        upload_id = location.rsplit("/", 1)[1]
        assert answer.headers["upload-href"] == f"/uploads/{upload_id}"
        assert stored_object(stack, upload_id) == data
        assert offset_of(client, location) == len(data)  # HEAD of a finished upload
        assert list((stack.data_dir / "uploads" / "resumable").glob(f"{upload_id}*")) == []


def test_a_checksum_mismatch_is_refused_and_the_offset_kept(stack: Stack, key: str,
                                                            las_file: Path) -> None:
    data = las_file.read_bytes()
    half = len(data) // 2
    with stack.client(key) as client:
        location = create(client, len(data))
        assert patch(client, location, 0, data[:half], sha("sha1", data[:half])).status_code == 204
        wrong = patch(client, location, half, data[half:], sha("sha1", data[half:] + b"x"))
        assert wrong.status_code == 460
        assert wrong.headers["content-type"] == "application/problem+json"
        assert wrong.json()["type"] == "/problems/checksum-mismatch"
        assert offset_of(client, location) == half
        unknown = patch(client, location, half, data[half:], "crc32 AAAAAA==")
        assert unknown.status_code == 400 and offset_of(client, location) == half
        right = patch(client, location, half, data[half:], sha("sha256", data[half:]))
        assert right.status_code == 204, right.text
        assert stored_object(stack, location.rsplit("/", 1)[1]) == data


def test_an_offset_mismatch_is_409(stack: Stack, key: str, las_file: Path) -> None:
    data = las_file.read_bytes()
    with stack.client(key) as client:
        location = create(client, len(data))
        assert patch(client, location, 0, data[:1000]).status_code == 204
        for wrong in (0, 999, 1001):
            answer = patch(client, location, wrong, data[wrong:2000])
            assert answer.status_code == 409, answer.text
            assert answer.json()["type"] == "/problems/offset-mismatch"
            assert answer.headers["upload-offset"] == "1000"
        assert offset_of(client, location) == 1000
        past = patch(client, location, 1000, data[1000:] + b"extra")
        assert past.status_code == 413 and offset_of(client, location) == 1000
        no_version = client.patch(location, content=b"x", headers=OCTETS |
                                  {"Upload-Offset": "1000"})
        assert no_version.status_code == 412 and no_version.headers["tus-version"] == "1.0.0"
        wrong_type = client.patch(location, content=b"x", headers=TUS | {
            "Upload-Offset": "1000", "Content-Type": "application/octet-stream"})
        assert wrong_type.status_code == 415
        assert client.delete(location, headers=TUS).status_code == 204
        assert client.head(location, headers=TUS).status_code == 404


def test_another_users_upload_is_not_found(stack: Stack, key: str, las_file: Path) -> None:
    data = las_file.read_bytes()
    other = stack.add_user("someone-else")
    with stack.client(key) as mine, stack.client(other) as theirs:
        location = create(mine, len(data))
        assert patch(mine, location, 0, data[:100]).status_code == 204
        assert theirs.head(location, headers=TUS).status_code == 404
        answer = patch(theirs, location, 100, data[100:])
        assert answer.status_code == 404 and answer.json()["type"] == "/problems/no-such-upload"
        assert theirs.delete(location, headers=TUS).status_code == 404
        href = "/uploads/" + location.rsplit("/", 1)[1]
        assert patch(mine, location, 100, data[100:]).status_code == 204
        refused = theirs.post("/processes/temporal/execution",
                              json={"inputs": {"cloud": {"href": href}}})
        assert refused.status_code == 422
        assert offset_of(mine, location) == len(data)
        assert httpx.head(f"{stack.url}{location}", headers=TUS).status_code == 401


def test_not_las_is_refused_at_its_first_bytes(stack: Stack, key: str) -> None:
    with stack.client(key) as client:
        location = create(client, 10_000, "notes.txt")
        answer = patch(client, location, 0, b"hello, this is not a point cloud")
        assert answer.status_code == 415, answer.text
        assert answer.json()["type"] == "/problems/unsupported-media-type"
        assert client.head(location, headers=TUS).status_code == 404


def test_sizes_above_the_limit_or_the_quota_are_413(stack: Stack) -> None:
    key = stack.add_user("quota-user")
    with stack.client(key) as client:
        too_big = client.post("/uploads/tus", headers=TUS | {"Upload-Length":
                                                             str(MAX_UPLOAD + 1)})
        assert too_big.status_code == 413 and too_big.json()["type"] == "/problems/file-too-large"
        first = create(client, MAX_UPLOAD)
        second = create(client, MAX_UPLOAD)
        refused = client.post("/uploads/tus", headers=TUS | {"Upload-Length": str(MAX_UPLOAD)})
        assert refused.status_code == 413  # 3 x 16 MB reserved would pass the 40 MB quota
        assert refused.json()["type"] == "/problems/storage-quota-exceeded"
        assert client.delete(first, headers=TUS).status_code == 204  # frees its reservation
        third = create(client, MAX_UPLOAD)
        for location in (second, third):
            assert client.delete(location, headers=TUS).status_code == 204


def test_an_expired_upload_is_gone_and_frees_its_bytes(stack: Stack) -> None:
    key = stack.add_user("slow-user")
    with stack.client(key) as client:
        stale = create(client, MAX_UPLOAD)
        assert patch(client, stale, 0, b"LASF" + bytes(100)).status_code == 204
        upload_id = stale.rsplit("/", 1)[1]
        part = stack.data_dir / "uploads" / "resumable" / f"{upload_id}.part"
        assert part.stat().st_size == 104
        engine = sa.create_engine(f"sqlite:///{stack.data_dir / 'service.sqlite3'}")
        with engine.begin() as db:
            db.execute(sa.text("UPDATE resumable_uploads SET expires = '2000-01-01T00:00:00.000Z'"
                               " WHERE id = :id"), {"id": upload_id})
        engine.dispose()
        gone = client.head(stale, headers=TUS)
        assert gone.status_code == 410
        # creating another removes the user's expired ones: their quota is free again
        for _ in range(2):
            create(client, MAX_UPLOAD)
        assert not part.exists()
        assert client.head(stale, headers=TUS).status_code == 404


def flags_of(client: httpx.Client, job_id: str, folder: Path) -> np.ndarray:
    answer = client.get(f"/jobs/{job_id}/results/cloud")
    assert answer.status_code == 200
    path = folder / f"{job_id}.las"
    path.write_bytes(answer.content)
    return np.asarray(laspy.read(path).outlier_flags)


def test_a_finished_upload_runs_as_a_job_like_a_plain_upload(stack: Stack, key: str,
                                                             las_file: Path,
                                                             tmp_path: Path) -> None:
    data = las_file.read_bytes()
    with stack.client(key) as client:
        location = create(client, len(data))
        third = len(data) // 3
        for start, end in ((0, third), (third, 2 * third), (2 * third, len(data))):
            assert patch(client, location, start, data[start:end],
                         sha("sha1", data[start:end])).status_code == 204
        plain = client.post("/uploads", params={"name": "scan.las"}, content=data)
        assert plain.status_code == 201
        jobs = {}
        for label, href in (("tus", "/uploads/" + location.rsplit("/", 1)[1]),
                            ("plain", plain.json()["href"])):
            answer = client.post("/processes/temporal/execution",
                                 json={"inputs": {"cloud": {"href": href}, "sigma": 0.01}})
            assert answer.status_code == 201, answer.text
            jobs[label] = answer.json()["jobID"]
        docs = {label: wait_job(client, job, ("successful", "failed"))
                for label, job in jobs.items()}
        assert all(d["status"] == "successful" for d in docs.values()), docs
        assert docs["tus"]["input_file"] == docs["plain"]["input_file"]
        flags = {label: flags_of(client, job, tmp_path) for label, job in jobs.items()}
        assert np.array_equal(flags["tus"], flags["plain"]) and flags["tus"].any()
        stats = {label: client.get(f"/jobs/{job}/results/statistics").json()["overall"]
                 for label, job in jobs.items()}
        assert stats["tus"]["points_flagged"] == stats["plain"]["points_flagged"]


class DroppingTransport(httpx.HTTPTransport):
    """Real HTTP that counts the body bytes sent and cuts the connection once, halfway
    through the body of the ``drop_at``-th PATCH."""

    def __init__(self, drop_at: int) -> None:
        super().__init__()
        self.drop_at = drop_at
        self.patches = 0
        self.sent = 0
        self.offsets: list[int] = []

    def handle_request(self, request: httpx.Request) -> httpx.Response:
        if request.method != "PATCH":
            return super().handle_request(request)
        self.patches += 1
        self.offsets.append(int(request.headers["upload-offset"]))
        body = request.read()
        cut = self.patches == self.drop_at

        def stream() -> Iterator[bytes]:
            half = len(body) // 2 if cut else len(body)
            self.sent += half
            yield body[:half]
            if cut:
                raise httpx.WriteError("connection dropped (simulated)")

        request.stream = _Stream(stream())
        return super().handle_request(request)


class _Stream(httpx.SyncByteStream):
    def __init__(self, parts: Iterator[bytes]) -> None:
        self.parts = parts

    def __iter__(self) -> Iterator[bytes]:
        yield from self.parts


def test_the_client_resumes_after_a_dropped_connection(stack: Stack, key: str,
                                                       tmp_path: Path) -> None:
    path = tmp_path / "big.las"
    write_cloud(path, n=30000, seed=22)
    size = path.stat().st_size
    chunk = 64 * 1024
    pieces = -(-size // chunk)
    transport = DroppingTransport(drop_at=pieces // 2 + 1)
    seen: list[tuple[int, int]] = []
    with Client(stack.url, key, transport=transport, chunk_bytes=chunk,
                retry_delay=0.05) as api:
        assert api.resumable()
        upload = api.upload(path, progress=lambda done, total: seen.append((done, total)))
    assert seen[-1] == (size, size)
    assert stored_object(stack, upload["id"]) == path.read_bytes()
    # after the cut every PATCH starts at or after the cut piece's offset: nothing before it
    # went again (a retry may meet the server still closing the cut request: 423, sent again)
    cut = pieces // 2
    cut_offset = transport.offsets[cut]
    assert transport.offsets[:cut + 1] == [i * chunk for i in range(cut + 1)]
    assert min(transport.offsets[cut + 1:]) == cut_offset
    assert sorted(set(transport.offsets)) == [i * chunk for i in range(pieces)]
    assert transport.sent - size <= chunk * (transport.patches - pieces)


def test_client_submit_uploads_resumably_and_removes_the_upload(stack: Stack, key: str,
                                                                las_file: Path) -> None:
    before = set((stack.data_dir / "uploads").glob("[0-9]*/*"))
    with Client(stack.url, key, chunk_bytes=50_000) as api, stack.client(key) as client:
        job = api.submit(las_file, "temporal", {"sigma": 0.01})
        done = api.wait(job["jobID"], timeout=180)
        assert done["input_file"]["name"] == "scan.las"
        # the job has its own copy; the upload made for it was deleted
        assert set((stack.data_dir / "uploads").glob("[0-9]*/*")) == before
        assert client.get(f"/jobs/{job['jobID']}/results/statistics").status_code == 200
    with Client(stack.url, key, resumable=False) as plain:  # the one-request fallback
        assert not plain.resumable()
        job = plain.submit(las_file, "temporal", {"sigma": 0.01})
        assert plain.wait(job["jobID"], timeout=180)["status"] == "successful"
    with Client(stack.url, "wrong-key", chunk_bytes=50_000) as api, \
            pytest.raises(ServiceError) as refused:
        api.upload(las_file)
    assert refused.value.status == 401


def documented_curl_loop() -> str:
    text = (ROOT / "docs" / "service.md").read_text()
    match = re.search(r"## Resumable uploads \(tus\).*?```sh\n(.*?)```", text, re.DOTALL)
    assert match, "docs/service.md has no curl example of resumable uploads"
    return match.group(1)


def test_documented_curl_example_runs(stack: Stack, key: str, las_file: Path,
                                  tmp_path: Path) -> None:
    script = documented_curl_loop()
    assert "CHUNK=67108864" in script
    script = script.replace("CHUNK=67108864", "CHUNK=30000")  # several pieces of a small file
    (tmp_path / "cloud.las").write_bytes(las_file.read_bytes())
    out = subprocess.run(["bash", "-eu", "-c", script], cwd=tmp_path,
                         env={"PATH": "/usr/bin:/bin", "API": stack.url, "KEY": key},
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    href = re.search(r'"href": "(/uploads/\w+)"', out.stdout).group(1)
    assert stored_object(stack, href.rsplit("/", 1)[1]) == las_file.read_bytes()
    with stack.client(key) as client:
        answer = client.post("/processes/temporal/execution",
                             json={"inputs": {"cloud": {"href": href}}})
        assert answer.status_code == 201, answer.text
