"""Every error case over HTTP, user isolation, dismissal of queued jobs and an API restart.

The stack here has an API and no worker, so submitted jobs stay queued (accepted) for as long as
a test needs them to.
"""

from __future__ import annotations

import json
from collections.abc import Iterator

import httpx
import pytest
from pydantic_core import to_jsonable_python

from lidar_outliers.detectors import DETECTORS
from lidar_outliers.params import PipelineParams
from tests.e2e.stack import RedisServer, Stack, assert_problem, running_stack
from tests.lasfiles import write_cloud

OGC = "http://www.opengis.net/def/exceptions/ogcapi-processes-1/1.0/"
LIMIT = 300_000


@pytest.fixture(scope="module")
def stack(redis_server: RedisServer, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Stack]:
    with running_stack(tmp_path_factory.mktemp("data"), redis_server.new_url(), workers=0,
                       max_active_jobs_per_user=2, max_upload_bytes=LIMIT,
                       retry_after_seconds=17) as s:
        yield s


@pytest.fixture(scope="module")
def keys(stack: Stack) -> dict[str, str]:
    return {name: stack.add_user(name) for name in ("alice", "bob", "carol")}


@pytest.fixture(scope="module")
def las_bytes(tmp_path_factory: pytest.TempPathFactory) -> bytes:
    path = tmp_path_factory.mktemp("in") / "scan.las"
    write_cloud(path, n=2000, seed=3)
    return path.read_bytes()


def submit(client: httpx.Client, data: bytes, inputs: dict | None = None,
           process: str = "temporal") -> httpx.Response:
    form = {"inputs": json.dumps(inputs)} if inputs is not None else {}
    return client.post(f"/processes/{process}/execution", files={"file": ("scan.las", data)},
                       data=form)


def test_processes_are_generated_from_the_models(stack: Stack) -> None:
    with stack.client() as client:
        ids = [p["id"] for p in client.get("/processes").json()["processes"]]
        assert set(DETECTORS) | {"pipeline"} <= set(ids)
        for name, detector in DETECTORS.items():
            model = detector.model
            doc = client.get(f"/processes/{name}").json()
            for field, info in model.model_fields.items():
                if field == "detector":
                    continue
                assert doc["inputs"][field]["schema"]["default"] == to_jsonable_python(
                    info.default), field  # JSON: the tuple origin of dror/snow is a list
            assert doc["inputs"]["noise_class"]["schema"]["default"] == 7
            assert "cloud" in doc["inputs"]
        pipeline = client.get("/processes/pipeline").json()
        assert set(PipelineParams.model_fields) <= set(pipeline["inputs"])
        assert client.get("/docs").status_code == 200
        assert client.get("/openapi.json").status_code == 200


def test_unknown_routes_and_methods_are_problems(stack: Stack) -> None:
    with stack.client() as client:
        assert_problem(client.get("/nowhere"), 404, "not-found")
        assert_problem(client.put("/processes"), 405, "method-not-allowed")
        body = assert_problem(client.get("/processes/nope"), 404, "no-such-process")
        assert body["type"] == OGC + "no-such-process"


def test_missing_wrong_and_revoked_keys(stack: Stack, las_bytes: bytes) -> None:
    with stack.client() as client:
        answer = client.get("/jobs")
        assert_problem(answer, 401, "unauthorized")
        assert answer.headers["www-authenticate"].startswith("Bearer")
        assert_problem(submit(client, las_bytes), 401, "unauthorized")
    with stack.client("lo_not-a-key") as client:
        assert_problem(client.get("/jobs"), 401, "unauthorized")
    key = stack.add_user("dave")
    with stack.client(key) as client:
        assert client.get("/jobs").status_code == 200
        stack.run_cli("users", "revoke", "dave")
        assert_problem(client.get("/jobs"), 401, "unauthorized")


def test_not_a_las_file_is_415_before_queueing(stack: Stack, keys: dict, las_bytes: bytes) -> None:
    with stack.client(keys["carol"]) as client:
        before = client.get("/jobs").json()["numberMatched"]
        body = assert_problem(submit(client, b"x,y,z\n1,2,3\n" * 100), 415,
                              "unsupported-media-type")
        assert "scan.las" in body["detail"]
        truncated = las_bytes[: len(las_bytes) // 2]
        assert_problem(submit(client, truncated), 415, "unsupported-media-type")
        assert_problem(client.post("/uploads", content=b"PK\x03\x04 zip"), 415,
                       "unsupported-media-type")
        assert client.get("/jobs").json()["numberMatched"] == before
        assert list((stack.data_dir / "uploads" / "incoming").glob("*")) == []


def test_too_large_is_413_while_streaming(stack: Stack, keys: dict, las_bytes: bytes) -> None:
    big = las_bytes + b"\0" * LIMIT
    with stack.client(keys["carol"]) as client:
        body = assert_problem(submit(client, big), 413, "file-too-large")
        assert str(LIMIT) in body["detail"]
        assert_problem(client.post("/uploads", content=big), 413, "file-too-large")
        assert list((stack.data_dir / "uploads" / "incoming").glob("*")) == []


def test_declared_size_over_the_limit_is_413_before_reading(stack: Stack, keys: dict) -> None:
    huge = b"\0" * (LIMIT + 2 * 1024**2)
    with stack.client(keys["carol"]) as client:
        assert_problem(submit(client, huge), 413, "file-too-large")
        assert_problem(client.post("/uploads", content=huge), 413, "file-too-large")
        # the connection was closed with the answer; the service still answers
        assert client.get("/jobs").status_code == 200


@pytest.mark.parametrize(
    ("process", "inputs", "parameter"),
    [
        ("temporal", {"n1": 0}, "n1"),
        ("temporal", {"n_1": 5}, "n_1"),
        ("temporal", {"sigma": -1}, "sigma"),
        ("patch", {"k": 20}, "k"),
        ("section", {"section_size": "big"}, "section_size"),
        ("pipeline", {"pipeline": [{"detector": "nope"}]}, "pipeline"),
        ("pipeline", {"noise_class": 300}, "noise_class"),
    ],
)
def test_bad_parameters_are_422_naming_the_parameter(
    stack: Stack, keys: dict, las_bytes: bytes, process: str, inputs: dict, parameter: str
) -> None:
    with stack.client(keys["carol"]) as client:
        body = assert_problem(submit(client, las_bytes, inputs, process), 422,
                              "invalid-parameter")
        assert parameter in body["detail"], body["detail"]


def test_a_stage_that_needs_gps_time_on_a_format_without_it_is_422(
    stack: Stack, keys: dict, tmp_path_factory: pytest.TempPathFactory
) -> None:
    path = tmp_path_factory.mktemp("pf0") / "no_time.las"
    write_cloud(path, n=500, point_format=0)
    with stack.client(keys["carol"]) as client:
        for process, inputs in (("temporal", None),
                                ("pipeline", {"pipeline": [{"detector": "patch"},
                                                           {"detector": "transient"}]})):
            body = assert_problem(submit(client, path.read_bytes(), inputs, process), 422,
                                  "invalid-parameter")
            assert "needs gps_time, which point format 0 does not have" in body["detail"]


def test_an_unclosed_json_string_is_a_400_and_the_api_keeps_serving(
    stack: Stack, keys: dict, las_bytes: bytes
) -> None:
    evil = '{"inputs": {"x": "' + '\\"' * 200_000  # 400 kB of \" and no closing quote
    with stack.client(keys["carol"]) as client:
        answer = client.post("/processes/dror/execution", content=evil,
                             headers={"Content-Type": "Application/JSON"})
        assert_problem(answer, 400, "invalid-parameter")
        form = client.post("/processes/temporal/execution",
                           files={"file": ("scan.las", las_bytes)}, data={"inputs": evil[10:]})
        assert_problem(form, 400, "invalid-parameter")
        assert client.get("/processes").status_code == 200  # this stack has no worker


def test_malformed_requests(stack: Stack, keys: dict, las_bytes: bytes) -> None:
    with stack.client(keys["carol"]) as client:
        answer = client.post("/processes/temporal/execution",
                             files={"file": ("scan.las", las_bytes)}, data={"inputs": "{n1: 5"})
        assert "inputs" in assert_problem(answer, 400, "invalid-parameter")["detail"]
        assert_problem(client.post("/processes/temporal/execution", data={"inputs": "{}"},
                                   files={"other": ("x", b"1")}), 400, "invalid-request")
        assert_problem(client.post("/processes/temporal/execution", content=b"raw",
                                   headers={"content-type": "text/plain"}), 415,
                       "unsupported-media-type")
        body = assert_problem(client.post("/processes/temporal/execution",
                                          json={"inputs": {"cloud": {"href": "/uploads/x"}}}),
                              422, "invalid-parameter")
        assert "cloud" in body["detail"]
        assert "limit" in assert_problem(client.get("/jobs", params={"limit": 0}), 422,
                                         "invalid-parameter")["detail"]


def test_limit_of_active_jobs_is_429_with_retry_after(
    stack: Stack, keys: dict, las_bytes: bytes
) -> None:
    with stack.client(keys["alice"]) as client:
        jobs = [submit(client, las_bytes) for _ in range(2)]
        assert [j.status_code for j in jobs] == [201, 201]
        answer = submit(client, las_bytes)
        assert_problem(answer, 429, "too-many-jobs")
        assert answer.headers["retry-after"] == "17"
        # another user is not affected by alice's limit
        with stack.client(keys["bob"]) as bob:
            assert submit(bob, las_bytes).status_code == 201

        # results of a queued job are not ready
        job = jobs[0].json()["jobID"]
        body = assert_problem(client.get(f"/jobs/{job}/results/cloud"), 404, "result-not-ready")
        assert body["type"] == OGC + "result-not-ready"
        assert_problem(client.get(f"/jobs/{job}/results"), 404, "result-not-ready")
        assert_problem(client.get(f"/jobs/{job}/results/statistics"), 404, "result-not-ready")

        # dismissing a queued job frees its slot and its files
        dismissed = client.delete(f"/jobs/{job}")
        assert dismissed.status_code == 200
        assert dismissed.json()["status"] == "dismissed"
        assert not (stack.data_dir / "jobs" / job).exists()
        assert client.get(f"/jobs/{job}").json()["status"] == "dismissed"
        assert submit(client, las_bytes).status_code == 201


def test_users_see_and_touch_only_their_own_jobs(
    stack: Stack, keys: dict, las_bytes: bytes
) -> None:
    with stack.client(keys["bob"]) as bob, stack.client(keys["carol"]) as carol:
        job = bob.get("/jobs").json()["jobs"][0]["jobID"]
        assert bob.get(f"/jobs/{job}").status_code == 200
        assert_problem(carol.get(f"/jobs/{job}"), 404, "no-such-job")
        assert_problem(carol.delete(f"/jobs/{job}"), 404, "no-such-job")
        assert_problem(carol.get(f"/jobs/{job}/results/cloud"), 404, "no-such-job")
        assert job not in {j["jobID"] for j in carol.get("/jobs").json()["jobs"]}
        assert bob.get(f"/jobs/{job}").json()["status"] == "accepted"
        # an upload of bob's cannot be used by carol
        href = bob.post("/uploads", content=las_bytes).json()["href"]
        body = assert_problem(carol.post("/processes/temporal/execution",
                                         json={"inputs": {"cloud": {"href": href}}}),
                              422, "invalid-parameter")
        assert "cloud.href" in body["detail"]


def test_health_without_worker_is_503(stack: Stack) -> None:
    with stack.client() as client:
        body = assert_problem(client.get("/health"), 503, "service-unavailable")
        assert "worker" in body["detail"]


def test_restart_of_the_api_keeps_jobs_and_keys(stack: Stack, keys: dict) -> None:
    with stack.client(keys["alice"]) as client:
        before = client.get("/jobs").json()
    assert before["numberMatched"] >= 3
    stack.stop_api()
    stack.start_api()
    with stack.client(keys["alice"]) as client:
        after = client.get("/jobs").json()
    assert after == before


def test_jobs_queued_without_a_worker_run_when_one_starts(
    stack: Stack, keys: dict, compiled_detectors: None
) -> None:
    from tests.e2e.stack import wait_job

    with stack.client(keys["bob"]) as client:
        queued = [j["jobID"] for j in client.get("/jobs").json()["jobs"]
                  if j["status"] == "accepted"]
        assert queued
        stack.start_worker()
        for job in queued:
            done = wait_job(client, job, ("successful", "failed"))
            assert done["status"] == "successful", done["message"]
