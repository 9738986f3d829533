"""A client that misbehaves, a disk that fills, many submissions at once: each case against the
real API process over HTTP, and the schema checked by schemathesis.

The stack here has no worker, so accepted jobs stay queued (and count as active) for as long
as a test needs them to.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import socket
import sqlite3
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from tests.e2e.stack import ROOT, RedisServer, Stack, assert_problem, running_stack, wait_job
from tests.lasfiles import write_cloud

ACTIVE_LIMIT = 4
NON_FINITE = ("1e400", "-1e400", "Infinity", "-Infinity", "NaN")


@pytest.fixture(scope="module")
def stack(redis_server: RedisServer, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Stack]:
    with running_stack(tmp_path_factory.mktemp("data"), redis_server.new_url(), workers=0,
                       max_active_jobs_per_user=ACTIVE_LIMIT) as s:
        yield s


@pytest.fixture(scope="module")
def las_bytes(tmp_path_factory: pytest.TempPathFactory) -> bytes:
    path = tmp_path_factory.mktemp("in") / "scan.las"
    write_cloud(path, n=1500, seed=5)
    return path.read_bytes()


def submit(client: httpx.Client, data: bytes, inputs: str | None = None,
           process: str = "pipeline") -> httpx.Response:
    form = {"inputs": inputs} if inputs is not None else {}
    return client.post(f"/processes/{process}/execution", files={"file": ("scan.las", data)},
                       data=form)


def post_json(client: httpx.Client, text: str, process: str = "pipeline") -> httpx.Response:
    return client.post(f"/processes/{process}/execution", content=text.encode(),
                       headers={"content-type": "application/json"})


def job_count(client: httpx.Client) -> int:
    return client.get("/jobs").json()["numberMatched"]


def leftover_parts(stack: Stack) -> list[Path]:
    incoming = stack.data_dir / "uploads" / "incoming"
    return list(incoming.glob("*.part")) if incoming.exists() else []


def test_non_finite_numbers_are_422_naming_the_field_and_create_no_job(
        stack: Stack, las_bytes: bytes) -> None:
    with stack.client(stack.add_user("nan-sender")) as client:
        href = client.post("/uploads", content=las_bytes).json()["href"]
        for number in NON_FINITE:
            pipeline = f'[{{"detector": "temporal", "sigma": {number}}}]'
            body = assert_problem(submit(client, las_bytes, f'{{"pipeline": {pipeline}}}'),
                                  422, "invalid-parameter")
            assert body["errors"][0]["parameter"] == "inputs.pipeline.0.sigma", body
            body = assert_problem(post_json(
                client, f'{{"inputs": {{"cloud": {{"href": "{href}"}}, "pipeline": {pipeline}}}}}'),
                422, "invalid-parameter")
            assert "inputs.pipeline.0.sigma" in body["detail"]
        assert job_count(client) == 0
    assert leftover_parts(stack) == []


def test_deeply_nested_inputs_are_a_400_problem(stack: Stack, las_bytes: bytes) -> None:
    deep = "[" * 100_000 + "]" * 100_000
    with stack.client(stack.add_user("nester")) as client:
        body = assert_problem(submit(client, las_bytes, f'{{"n1": {deep}}}', "temporal"), 400,
                              "invalid-parameter")
        assert "nested deeper" in body["detail"]
        body = assert_problem(post_json(client, f'{{"inputs": {{"cloud": {deep}}}}}'), 400,
                              "invalid-parameter")
        assert "nested deeper" in body["detail"]
        # nesting a real request needs (a pipeline of stages) is fine
        assert submit(client, las_bytes, '{"pipeline": [{"detector": "temporal"}]}'
                      ).status_code == 201
        assert job_count(client) == 1


def test_huge_integers_are_422(stack: Stack, las_bytes: bytes) -> None:
    with stack.client(stack.add_user("big-numbers")) as client:
        for query in ("offset=9223372036854775808", "limit=9223372036854775808",
                      "offset=" + "9" * 5000):
            body = assert_problem(client.get(f"/jobs?{query}"), 422, "invalid-parameter")
            assert query.split("=")[0] in body["detail"]
        for number in ("9223372036854775808", "1" + "0" * 5000, "-" + "9" * 40):
            body = assert_problem(submit(client, las_bytes, f'{{"n1": {number}}}', "temporal"),
                                  422, "invalid-parameter")
            assert body["errors"][0]["parameter"] == "inputs.n1", body
        assert_problem(client.get("/jobs/x/results/points?max_points=" + "9" * 30), 422,
                       "invalid-parameter")
        assert job_count(client) == 0


def test_empty_files_are_refused_as_empty(stack: Stack) -> None:
    with stack.client(stack.add_user("empty-sender")) as client:
        body = assert_problem(client.post("/uploads?name=nothing.las", content=b""), 400,
                              "empty-file")
        assert "empty" in body["detail"] and "nothing.las" in body["detail"]
        body = assert_problem(client.post("/processes/temporal/execution",
                                          files={"file": ("void.las", b"")}), 400, "empty-file")
        assert "empty" in body["detail"] and "void.las" in body["detail"]
        assert job_count(client) == 0
    assert leftover_parts(stack) == []


def test_status_polls_check_the_key_and_the_owner(stack: Stack, las_bytes: bytes) -> None:
    owner = stack.add_user("poll-owner")
    with stack.client(owner) as client:
        job = submit(client, las_bytes).json()["jobID"]
        assert client.get(f"/jobs/{job}").json()["status"] == "accepted"
    with stack.client(stack.add_user("poll-other")) as other:
        assert_problem(other.get(f"/jobs/{job}"), 404, "no-such-job")
    with stack.client("lo_wrong") as wrong:
        assert_problem(wrong.get(f"/jobs/{job}"), 401, "unauthorized")
    with stack.client() as anonymous:
        assert_problem(anonymous.get(f"/jobs/{job}"), 401, "unauthorized")
    stack.run_cli("users", "revoke", "poll-owner")
    with stack.client(owner) as client:  # at once: no key is remembered by the API
        assert_problem(client.get(f"/jobs/{job}"), 401, "unauthorized")


def test_docs_and_redoc_load_only_local_files(stack: Stack) -> None:
    with stack.client() as client:
        for page in ("/docs", "/redoc"):
            html = client.get(page)
            assert html.status_code == 200
            urls = re.findall(r"""(?:src|href|url)\s*[:=]\s*['"]([^'"]+)['"]""", html.text)
            assert urls and all(u.startswith("/") and not u.startswith("//") for u in urls), urls
            assert "http://" not in html.text and "https://" not in html.text
            for url in urls:
                asset = client.get(url)
                assert asset.status_code == 200 and len(asset.content) > 100, url


def test_every_answer_carries_security_headers(stack: Stack) -> None:
    with stack.client() as client:
        for path in ("/", "/jobs", "/docs", "/openapi.json", "/no-such-route",
                     "/docs/static/swagger-ui.css", "/app/static/app.js"):
            headers = client.get(path).headers
            assert headers["x-content-type-options"] == "nosniff", path
            assert headers["referrer-policy"] == "no-referrer", path
            assert headers["x-frame-options"] == "DENY", path
            assert "frame-ancestors 'none'" in headers["content-security-policy"], path
        page = client.get("/app").headers["content-security-policy"]
        assert "default-src 'none'" in page and "script-src 'self'" in page  # its own policy


def test_health_without_a_key_reveals_nothing_internal(stack: Stack) -> None:
    internal = [socket.gethostname(), "127.0.0.1", "redis://", "sqlite", str(stack.data_dir),
                "@"]
    with stack.client() as client:
        answer = client.get("/health")
        body = assert_problem(answer, 503, "service-unavailable")  # no worker here
        assert "worker" in body["detail"] and body["workers"] == 0
        assert not [word for word in internal if word in answer.text], answer.text
    with stack.client(stack.add_user("operator")) as client:
        body = assert_problem(client.get("/health"), 503, "service-unavailable")
        assert body["workers"] == [] and body["redis"] == "ok"
    with stack.client("lo_wrong") as client:
        assert_problem(client.get("/health"), 401, "unauthorized")


def test_concurrent_submissions_never_exceed_the_active_limit(
        stack: Stack, las_bytes: bytes) -> None:
    keys = {name: stack.add_user(name) for name in ("rush-a", "rush-b", "rush-c")}
    answers: list[tuple[str, int]] = []
    start = threading.Barrier(30)

    def send(name: str) -> None:
        with stack.client(keys[name]) as client:
            start.wait()
            answers.append((name, submit(client, las_bytes).status_code))

    threads = [threading.Thread(target=send, args=(name,)) for name in keys for _ in range(10)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert len(answers) == 30 and {code for _, code in answers} <= {201, 429}, answers
    for name, key in keys.items():
        accepted = sum(1 for n, code in answers if n == name and code == 201)
        with stack.client(key) as client:
            statuses = [j["status"] for j in client.get("/jobs").json()["jobs"]]
        assert accepted == len(statuses) == ACTIVE_LIMIT, (name, accepted, statuses)
        assert set(statuses) == {"accepted"}


def test_users_add_names_the_store_it_wrote_to(stack: Stack, tmp_path: Path) -> None:
    out = stack.run_cli("users", "add", "store-finder")
    key = out.strip().splitlines()[-1]
    assert f"sqlite:///{stack.data_dir.resolve() / 'service.sqlite3'}" in out
    with stack.client(key) as client:
        assert client.get("/jobs").status_code == 200
    # another DATA_DIR: a new store, and a note saying so
    elsewhere = subprocess.run(
        [sys.executable, "-m", "lidar_outliers", "users", "add", "lost"], cwd=ROOT,
        env=dict(stack.env, DATA_DIR=str(tmp_path / "elsewhere")), capture_output=True,
        text=True, timeout=60, check=True)
    assert str(tmp_path / "elsewhere" / "service.sqlite3") in elsewhere.stdout
    assert "no store existed" in elsewhere.stderr and "DATA_DIR" in elsewhere.stderr
    with stack.client(elsewhere.stdout.strip().splitlines()[-1]) as client:
        assert_problem(client.get("/jobs"), 401, "unauthorized")


#: Requests that are schema-valid and yet refused for what they hold: a file that is not LAS/LAZ
#: (415), a trajectory or an upload href the server does not know (422), a busy user (429); a
#: job filter the schema cannot judge (a 31st of February, an interval that ends before it
#: starts: 400); a resumable upload's state (gone 404/410, another offset 409, busy 423). tus
#: answers a request without its version header with 412.
SCHEMATHESIS_CONFIG = """
[[operations]]
include-path-regex = "^/(uploads|processes/\\\\{process_id\\\\}/execution)$"
include-method = "POST"
checks.positive_data_acceptance.expected-statuses = ["2xx", "401", "404", "413", "415", "422",
                                                     "429"]

[[operations]]
include-operation-id = "list_jobs_jobs_get"
checks.positive_data_acceptance.expected-statuses = ["2xx", "400", "401"]

[[operations]]
include-path-regex = "^/uploads/tus"
checks.positive_data_acceptance.expected-statuses = ["2xx", "400", "401", "404", "409", "410",
                                                     "413", "423"]
# tus answers a missing or other protocol version with 412, as the protocol says
checks.negative_data_rejection.expected-statuses = ["400", "401", "404", "409", "412", "413",
                                                    "415", "422"]
checks.missing_required_header.expected-statuses = ["400", "401", "412", "422"]
"""


def test_schemathesis_finds_no_failure(stack: Stack, tmp_path: Path) -> None:
    """Every documented operation with a key: no 5xx, only documented statuses and media types,
    schema-valid requests accepted, invalid ones refused. /health is left out: without a
    worker it answers 503 by design (tested above). A resumable upload's PATCH is left out too:
    its body type (application/offset+octet-stream) is one schemathesis cannot send; the
    resumable-upload tests drive it."""
    st = Path(sys.executable).parent / "st"
    if not st.exists():
        pytest.skip(f"schemathesis is not installed ({st}); `pip install -e .[test]`")
    config = tmp_path / "schemathesis.toml"
    config.write_text(SCHEMATHESIS_CONFIG)
    key = stack.add_user("schemathesis")
    run = subprocess.run(
        [str(st), "--config-file", str(config), "run", f"{stack.url}/openapi.json",
         "-H", f"Authorization: Bearer {key}", "--max-examples", "5",
         "--phases", "examples,coverage,fuzzing", "--workers", "1", "--seed", "1",
         "--request-timeout", "60", "--exclude-path", "/health", "--exclude-method", "PATCH",
         "--no-color"],
        capture_output=True, text=True, timeout=900, cwd=tmp_path)
    assert run.returncode == 0, run.stdout[-6000:] + run.stderr[-2000:]
    assert re.search(r"\d+ passed", run.stdout), run.stdout[-2000:]


# ---- a full disk ---------------------------------------------------------------------------

def _mount_small_disk(folder: Path, size: str) -> None:
    if os.geteuid() != 0 or not shutil.which("mount"):
        pytest.skip("the full-disk test mounts a small tmpfs as DATA_DIR, which needs root "
                    "(it runs as root in CI)")
    folder.mkdir(parents=True)
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs",
                              str(folder)], capture_output=True, text=True)
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here (a container without CAP_SYS_ADMIN?): "
                    f"{mounted.stderr.strip()}")


def _fill(folder: Path, leave: int) -> Path:
    """A ballast file that leaves about ``leave`` bytes free on ``folder``'s disk."""
    ballast = folder / "ballast"
    free = shutil.disk_usage(folder).free
    with open(ballast, "wb") as out:
        out.write(b"\0" * max(0, free - leave))
    return ballast


def _rows(database: Path, table: str) -> int:
    with sqlite3.connect(database) as db:
        return db.execute(f"SELECT count(*) FROM {table}").fetchone()[0]


@pytest.fixture
def small_disk(tmp_path: Path) -> Iterator[Path]:
    folder = tmp_path / "small"
    _mount_small_disk(folder, "24m")
    yield folder
    subprocess.run(["umount", "-l", str(folder)], check=False)


def test_full_disk_answers_507_keeps_nothing_half_written_and_recovers(
        redis_server: RedisServer, small_disk: Path, tmp_path: Path) -> None:
    cloud = tmp_path / "big.las"
    write_cloud(cloud, n=40_000, seed=1)  # about 1.4 MB
    data = cloud.read_bytes()
    margin = 512 * 1024
    with running_stack(small_disk, redis_server.new_url(), workers=0,
                       min_free_bytes=margin) as stack:
        database = small_disk / "service.sqlite3"
        key = stack.add_user("filler")
        with stack.client(key) as client:
            href = client.post("/uploads", content=data).json()["href"]
            queued = post_json(client, f'{{"inputs": {{"cloud": {{"href": "{href}"}}, '
                                       f'"sigma": 0.01}}}}', "temporal")
            assert queued.status_code == 201, queued.text
            uploads_before = _rows(database, "uploads")

            ballast = _fill(small_disk, leave=margin + 300 * 1024)
            # refused before a byte is read: no room for the file and its result
            body = assert_problem(client.post("/uploads", content=data), 507,
                                  "insufficient-storage")
            assert "MIN_FREE_BYTES" in body["detail"]
            assert_problem(submit(client, data, process="temporal"), 507,
                           "insufficient-storage")
            # no declared length: refused when the disk runs out while it arrives
            body = assert_problem(client.post("/uploads", content=iter([data] * 4)), 507,
                                  "insufficient-storage")
            assert "full" in body["detail"]
            assert leftover_parts(stack) == [] and _rows(database, "uploads") == uploads_before
            assert client.get("/jobs").status_code == 200  # reading goes on

            # a worker that finds no room for the result fails the job and says why
            stack.start_worker()
            stack.wait_workers_ready()
            done = wait_job(client, queued.json()["jobID"], ("successful", "failed"), 300)
            assert done["status"] == "failed" and "disk is full" in done["message"], done
            scratch = small_disk / "scratch"
            assert not scratch.exists() or not [p for p in scratch.rglob("*") if p.is_file()]

            # space comes back: everything works again without a restart
            ballast.unlink()
            again = client.post("/uploads", content=data)
            assert again.status_code == 201, again.text
            job = post_json(client, f'{{"inputs": {{"cloud": {{"href": '
                                    f'"{again.json()["href"]}"}}, "sigma": 0.01}}}}',
                            "temporal").json()["jobID"]
            assert wait_job(client, job, ("successful", "failed"), 300)["status"] == \
                "successful"
            assert json.loads(client.get("/health").text)["status"] == "ok"
