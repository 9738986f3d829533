"""OGC API - Processes - Part 1 over HTTP against the real stack (uvicorn, Celery, Redis): one
test (or more) per conformance class declared at /conformance, the documents checked against
the standard's published schemas (tests/data/ogc-schemas); CORS for the configured origins."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from openapi_spec_validator import validate as validate_openapi

from tests.e2e.stack import RedisServer, Stack, running_stack, wait_job
from tests.lasfiles import untimed_cloud, write_cloud
from tests.ogc_schemas import check
from tests.receiver import Receiver

CONF = "http://www.opengis.net/spec/ogcapi-processes-1/1.0/conf/"
REL = "http://www.opengis.net/def/rel/ogc/1.0/"
PORTAL = "https://portal.example"
BROWSER_ACCEPT = "text/html,application/xhtml+xml,application/xml;q=0.9,*/*;q=0.8"
SYNC_MAX_POINTS = 3000


@pytest.fixture(scope="module")
def stack(redis_server: RedisServer, tmp_path_factory: pytest.TempPathFactory,
          compiled_detectors: None) -> Iterator[Stack]:
    with running_stack(tmp_path_factory.mktemp("data"), redis_server.new_url(),
                       max_active_jobs_per_user=8, cors_origins=f"{PORTAL},https://b.example",
                       callback_allow="127.0.0.1", sync_max_points=SYNC_MAX_POINTS) as s:
        yield s


@pytest.fixture(scope="module")
def key(stack: Stack) -> str:
    return stack.add_user("ogc")


@pytest.fixture(scope="module")
def small(tmp_path_factory: pytest.TempPathFactory) -> bytes:
    path = tmp_path_factory.mktemp("in") / "small.las"
    write_cloud(path, n=1500, seed=3)
    return path.read_bytes()


@pytest.fixture
def receiver() -> Iterator[Receiver]:
    server = Receiver(fail_first=1)  # the first callback is answered 503: it is retried
    yield server
    server.close()


def execute(client: httpx.Client, data: bytes, name: str = "small.las", *,
            headers: dict[str, str] | None = None, process: str = "temporal",
            **fields: Any) -> httpx.Response:
    form = {"inputs": json.dumps({"sigma": 0.01})} | {k: json.dumps(v) for k, v in fields.items()}
    return client.post(f"/processes/{process}/execution", files={"file": (name, data)},
                       data=form, headers=headers or {})


def rels(doc: dict) -> dict[str, dict]:
    return {link["rel"]: link for link in doc["links"]}


# ---- core, json ------------------------------------------------------------------------------

def test_landing_page_links_the_api_conformance_processes_and_jobs(stack: Stack) -> None:
    with stack.client() as client:
        doc = client.get("/").json()
        check("landingPage", doc)
        links = rels(doc)
        assert links["service-desc"]["href"] == "/api"
        assert links["service-desc"]["type"] == "application/vnd.oai.openapi+json;version=3.0"
        for rel in ("service-desc", "service-doc", REL + "conformance", REL + "processes"):
            assert client.get(links[rel]["href"]).status_code == 200, rel
        assert links[REL + "job-list"]["href"] == "/jobs"
        assert client.get("/jobs").status_code == 401  # the job list is the caller's


def test_conformance_declares_all_eight_classes_of_part_1(stack: Stack) -> None:
    with stack.client() as client:
        doc = client.get("/conformance").json()
    check("confClasses", doc)
    assert sorted(doc["conformsTo"]) == sorted(CONF + c for c in (
        "core", "ogc-process-description", "json", "html", "oas30", "job-list", "callback",
        "dismiss"))


# ---- ogc-process-description -----------------------------------------------------------------

def test_process_list_and_descriptions_follow_the_schemas(stack: Stack) -> None:
    with stack.client() as client:
        listing = client.get("/processes").json()
        check("processList", listing)
        assert listing["processes"]
        for summary in listing["processes"]:
            check("processSummary", summary)
            description = client.get(f"/processes/{summary['id']}").json()
            check("process", description)
            assert description["jobControlOptions"] == ["sync-execute", "async-execute",
                                                        "dismiss"]
            assert rels(description)[REL + "execute"]["href"].endswith("/execution")


# ---- oas30 -----------------------------------------------------------------------------------

def test_the_api_definition_is_valid_openapi_3_0(stack: Stack) -> None:
    with stack.client() as client:
        answer = client.get("/api")
    assert answer.headers["content-type"] == "application/vnd.oai.openapi+json;version=3.0"
    document = answer.json()
    assert document["openapi"].startswith("3.0.")
    validate_openapi(document)
    assert {"/", "/conformance", "/processes", "/processes/{process_id}",
            "/processes/{process_id}/execution", "/jobs", "/jobs/{job_id}",
            "/jobs/{job_id}/results"} <= set(document["paths"])
    parameters = {p["name"] for p in document["paths"]["/jobs"]["get"]["parameters"]}
    assert {"type", "processID", "status", "datetime", "minDuration", "maxDuration",
            "limit"} <= parameters


# ---- html ------------------------------------------------------------------------------------

def test_html_for_browsers_json_by_default(stack: Stack, key: str, small: bytes) -> None:
    hostile = "<b onmouseover=alert(1)>x.las"
    with stack.client(key) as client:
        job = execute(client, small, hostile).json()["jobID"]
        for path in ("/", "/conformance", "/processes", "/processes/temporal", "/jobs",
                     f"/jobs/{job}"):
            json_answer = client.get(path)
            assert json_answer.headers["content-type"] == "application/json", path
            for answer in (client.get(path, headers={"Accept": BROWSER_ACCEPT}),
                           client.get(path, params={"f": "html"})):
                assert answer.status_code == 200, path
                assert answer.headers["content-type"].startswith("text/html"), path
                assert answer.text.startswith("<!DOCTYPE html>")
                assert "<b " not in answer.text, path  # escaped, never markup
        page = client.get(f"/jobs/{job}?f=html").text
        assert "&lt;b onmouseover=alert(1)&gt;x.las" in page
        assert client.get("/processes?f=json", headers={"Accept": BROWSER_ACCEPT}).headers[
            "content-type"] == "application/json"
        bad = client.get("/processes", params={"f": "xml"})
        assert bad.status_code == 400 and bad.json()["errors"][0]["parameter"] == "f"
        wait_job(client, job, ("successful", "failed"))


# ---- core: Prefer, asynchronous and synchronous execution -----------------------------------

def test_respond_async_is_applied_and_the_documents_follow_the_schemas(
    stack: Stack, key: str, small: bytes
) -> None:
    with stack.client(key) as client:
        answer = execute(client, small, headers={"Prefer": "respond-async"})
        assert answer.status_code == 201
        assert answer.headers["preference-applied"] == "respond-async"
        job = answer.json()
        check("statusInfo", job)
        assert answer.headers["location"] == f"/jobs/{job['jobID']}"
        done = wait_job(client, job["jobID"], ("successful", "failed"))
        check("statusInfo", done)
        assert done["status"] == "successful"
        results = client.get(f"/jobs/{job['jobID']}/results").json()
        check("results", results)
        assert client.get(results["cloud"]["href"]).status_code == 200
        # no preference: asynchronous, nothing reported applied
        plain = execute(client, small)
        assert plain.status_code == 201 and "preference-applied" not in plain.headers
        wait_job(client, plain.json()["jobID"], ("successful", "failed"))


def test_prefer_wait_runs_a_small_cloud_synchronously(stack: Stack, key: str, small: bytes,
                                                      tmp_path: Path) -> None:
    with stack.client(key) as client:
        answer = execute(client, small, headers={"Prefer": "wait=100"})
        assert answer.status_code == 200, answer.text
        assert answer.headers["preference-applied"] == "wait=100"
        results = answer.json()
        check("results", results)
        cloud = client.get(results["cloud"]["href"])
        assert cloud.status_code == 200 and cloud.headers["content-type"] == "application/vnd.las"
        # above SYNC_MAX_POINTS the preference is not honoured: an asynchronous job
        big = tmp_path / "big.las"
        write_cloud(big, n=SYNC_MAX_POINTS + 1)
        answer = execute(client, big.read_bytes(), headers={"Prefer": "wait"})
        assert answer.status_code == 201 and "preference-applied" not in answer.headers
        wait_job(client, answer.json()["jobID"], ("successful", "failed"))
        # a job failing synchronously is a problem naming the job
        no_time = tmp_path / "no_time.las"
        untimed_cloud(no_time)
        failed = execute(client, no_time.read_bytes(), headers={"Prefer": "wait"})
        assert failed.status_code == 422 and failed.json()["type"] == "/problems/job-failed"
        assert "gps_time" in failed.json()["detail"]


# ---- job-list --------------------------------------------------------------------------------

def test_job_list_filters(stack: Stack, small: bytes, tmp_path: Path) -> None:
    key = stack.add_user("lister")
    no_time = tmp_path / "no_time.las"
    untimed_cloud(no_time)
    with stack.client(key) as client:
        ok = execute(client, small).json()["jobID"]
        bad = execute(client, no_time.read_bytes()).json()["jobID"]
        section = execute(client, small, process="section",
                          inputs={}).json()["jobID"]
        for job in (ok, bad, section):
            wait_job(client, job, ("successful", "failed"))
        dismissed = client.delete(f"/jobs/{section}").json()
        assert dismissed["status"] == "dismissed"

        def ids(**params: Any) -> list[str]:
            answer = client.get("/jobs", params=params)
            assert answer.status_code == 200, answer.text
            check("jobList", answer.json())
            return [j["jobID"] for j in answer.json()["jobs"]]

        assert ids() == [section, bad, ok]  # newest first
        assert ids(processID="temporal") == [bad, ok]
        assert ids(processID=["section", "temporal"]) == [section, bad, ok]
        assert ids(status="failed") == [bad]
        assert ids(status=["successful", "dismissed"]) == [section, ok]
        assert ids(status="successful,failed") == [bad, ok]
        created = client.get(f"/jobs/{ok}").json()["created"]
        assert ids(datetime=f"{created}/..") == [section, bad, ok]
        assert ids(datetime=f"../{created}") == [ok]
        assert ids(datetime=created) == [ok]
        assert ids(datetime="2000-01-01T00:00:00Z/2000-01-02T00:00:00+00:00") == []
        assert ids(minDuration=0) == [section, bad, ok]
        assert ids(minDuration=3600) == []
        assert ids(maxDuration=3600, status="successful") == [ok]
        assert ids(type="process", status="failed") == [bad]
        assert ids(type="openeo") == []

        page = client.get("/jobs", params={"status": "successful,failed", "limit": 1}).json()
        assert [j["jobID"] for j in page["jobs"]] == [bad] and page["numberMatched"] == 2
        assert rels(page)["alternate"]["type"] == "text/html"
        following = client.get(rels(page)["next"]["href"]).json()
        assert [j["jobID"] for j in following["jobs"]] == [ok]
        assert "prev" in rels(following) and "next" not in rels(following)

        for params, named in (({"status": "done"}, "status"), ({"datetime": "yesterday"},
                              "datetime"), ({"datetime": "../.."}, "datetime"),
                              ({"minDuration": 10, "maxDuration": 5}, "minDuration"),
                              ({"minDuration": -1}, "minDuration"), ({"limit": 0}, "limit")):
            answer = client.get("/jobs", params=params)
            assert 400 <= answer.status_code < 500, params
            assert answer.headers["content-type"] == "application/problem+json"
            assert named in answer.json()["detail"], params


# ---- callback --------------------------------------------------------------------------------

def test_subscriber_callbacks_reach_a_local_server_with_retries(
    stack: Stack, key: str, small: bytes, receiver: Receiver, tmp_path: Path
) -> None:
    hooks = {"successUri": receiver.url + "/ok", "inProgressUri": receiver.url + "/running",
             "failedUri": receiver.url + "/failed"}
    with stack.client(key) as client:
        job = execute(client, small, subscriber=hooks).json()["jobID"]
        results = receiver.wait_for("/ok")[0]
        check("results", results)
        # the links are absolute: the receiver may fetch them
        assert results["cloud"]["href"] == f"{stack.url}/jobs/{job}/results/cloud"
        assert client.get(results["statistics"]["href"]).status_code == 200
        started = receiver.posts("/running")
        # the first POST was answered 503 and sent again
        assert len(started) == 2 and started[0] == started[1]
        check("statusInfo", started[0])
        assert started[0]["jobID"] == job and started[0]["status"] == "running"

        no_time = tmp_path / "no_time.las"
        untimed_cloud(no_time)
        job = execute(client, no_time.read_bytes(), subscriber=hooks).json()["jobID"]
        failed = receiver.wait_for("/failed")[0]
        check("statusInfo", failed)
        assert failed["jobID"] == job and failed["status"] == "failed"
        assert "gps_time" in failed["message"]
        assert len(receiver.posts("/ok")) == 1


@pytest.mark.parametrize("target", ["http://localhost:{port}/ok", "http://10.0.0.1/ok",
                                    "http://169.254.169.254/latest", "http://[::1]:{port}/"])
def test_callbacks_to_internal_targets_are_refused(stack: Stack, key: str, small: bytes,
                                                   receiver: Receiver, target: str) -> None:
    # CALLBACK_ALLOW lists 127.0.0.1 only: "localhost" is judged by what it resolves to
    url = target.format(port=receiver.server.server_address[1])
    with stack.client(key) as client:
        before = client.get("/jobs").json()["numberMatched"]
        answer = execute(client, small, subscriber={"successUri": url})
        assert answer.status_code == 422
        problem = answer.json()
        assert problem["errors"][0]["parameter"] == "subscriber.successUri"
        assert "public" in problem["detail"] or "CALLBACK_ALLOW" in problem["detail"]
        assert client.get("/jobs").json()["numberMatched"] == before  # no job made
    assert receiver.received == []


# ---- dismiss ---------------------------------------------------------------------------------

def test_dismiss_answers_the_status_document_with_status_dismissed(
    stack: Stack, key: str, small: bytes
) -> None:
    with stack.client(key) as client:
        job = execute(client, small).json()["jobID"]
        wait_job(client, job, ("successful", "failed"))
        answer = client.delete(f"/jobs/{job}")
        assert answer.status_code == 200
        check("statusInfo", answer.json())
        assert answer.json()["status"] == "dismissed"
        assert client.get(f"/jobs/{job}").json()["status"] == "dismissed"
        assert client.get(f"/jobs/{job}/results").status_code == 404
        assert client.delete("/jobs/no-such-job").status_code == 404


# ---- CORS ------------------------------------------------------------------------------------

def test_cors_for_the_configured_origins_only(stack: Stack, key: str, small: bytes) -> None:
    preflight = {"Access-Control-Request-Method": "POST",
                 "Access-Control-Request-Headers": "authorization, content-type, prefer"}
    with stack.client(key) as client:
        answer = client.options("/processes/temporal/execution",
                                headers={"Origin": PORTAL, **preflight})
        assert answer.status_code in (200, 204)
        assert answer.headers["access-control-allow-origin"] == PORTAL
        assert "POST" in answer.headers["access-control-allow-methods"]
        assert "prefer" in answer.headers["access-control-allow-headers"]
        refused = client.options("/processes/temporal/execution",
                                 headers={"Origin": "https://evil.example", **preflight})
        assert not any(h.startswith("access-control-") for h in refused.headers)

        made = execute(client, small, headers={"Origin": PORTAL, "Prefer": "respond-async"})
        assert made.headers["access-control-allow-origin"] == PORTAL
        exposed = {h.strip().lower() for h in
                   made.headers["access-control-expose-headers"].split(",")}
        assert {"location", "preference-applied", "content-range"} <= exposed
        assert "origin" in made.headers["vary"].lower()
        problem = client.get("/jobs/nope", headers={"Origin": PORTAL})  # errors too
        assert problem.status_code == 404
        assert problem.headers["access-control-allow-origin"] == PORTAL
        plain = client.get("/processes", headers={"Origin": "https://evil.example"})
        assert "access-control-allow-origin" not in plain.headers
        wait_job(client, made.json()["jobID"], ("successful", "failed"))
