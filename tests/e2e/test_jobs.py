"""End to end over HTTP with one API and one Celery worker: upload, poll, download, check."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import laspy
import numpy as np
import pytest

from tests.e2e.stack import RedisServer, Stack, running_stack, wait_job
from tests.lasfiles import untimed_cloud, write_cloud


@pytest.fixture(scope="module")
def stack(redis_server: RedisServer, tmp_path_factory: pytest.TempPathFactory,
          compiled_detectors: None) -> Iterator[Stack]:
    with running_stack(tmp_path_factory.mktemp("data"), redis_server.new_url(),
                       max_active_jobs_per_user=8) as s:
        yield s


@pytest.fixture(scope="module")
def key(stack: Stack) -> str:
    return stack.add_user("alice")


@pytest.fixture(scope="module")
def las_file(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, np.ndarray]:
    path = tmp_path_factory.mktemp("in") / "scan.las"
    spikes = write_cloud(path, n=4000, seed=1)
    return path, spikes


def test_multipart_las_round_trip(stack: Stack, key: str, las_file, tmp_path: Path) -> None:
    path, spikes = las_file
    with stack.client(key) as client:
        answer = client.post(
            "/processes/temporal/execution",
            files={"file": ("scan.las", path.read_bytes(), "application/octet-stream")},
            data={"inputs": json.dumps({"n1": 5, "n2": 5, "sigma": 0.01})},
        )
        assert answer.status_code == 201, answer.text
        doc = answer.json()
        assert answer.headers["location"] == f"/jobs/{doc['jobID']}"
        assert doc["status"] in ("accepted", "running")
        assert doc["processID"] == "temporal"
        assert doc["inputs"]["pipeline"][0]["n1"] == 5
        assert doc["input_file"]["points"] == 4000
        assert doc["input_file"]["name"] == "scan.las"
        assert doc["input_file"]["point_format"] == 1

        done = wait_job(client, doc["jobID"], ("successful", "failed"))
        assert done["status"] == "successful", done["message"]
        assert done["progress"] == 100
        assert done["started"] and done["finished"]

        results = client.get(f"/jobs/{doc['jobID']}/results").json()
        cloud = client.get(results["cloud"]["href"])
        assert cloud.status_code == 200
        assert cloud.headers["content-type"] == "application/vnd.las"
        out = tmp_path / "out.las"
        out.write_bytes(cloud.content)
        las = laspy.read(out)
        original = laspy.read(path)
        assert len(las.points) == 4000
        np.testing.assert_array_equal(las.x, original.x)
        np.testing.assert_array_equal(las.gps_time, original.gps_time)
        assert {"outlier_flags", "temporal_score"} <= set(las.point_format.extra_dimension_names)
        flagged = np.flatnonzero(np.asarray(las.outlier_flags) & 1)
        assert set(spikes) <= set(flagged)  # every 2 m spike is found
        assert np.all(np.asarray(las.classification)[flagged] == 7)

        stats = client.get(results["statistics"]["href"])
        assert stats.status_code == 200
        assert stats.headers["content-type"].startswith("application/json")
        assert "temporal" in json.dumps(stats.json())

        preview = client.get(results["preview"]["href"])
        assert preview.status_code == 200, preview.text
        assert preview.headers["content-type"] == "image/png"
        assert preview.content.startswith(b"\x89PNG")


def test_laz_in_laz_out_and_filters(stack: Stack, key: str, tmp_path: Path) -> None:
    path = tmp_path / "scan.laz"
    spikes = write_cloud(path, n=3000, seed=2, laz=True, point_format=3)
    with stack.client(key) as client:
        answer = client.post("/processes/temporal/execution",
                             files={"file": ("scan.laz", path.read_bytes())})
        assert answer.status_code == 201, answer.text
        job = answer.json()["jobID"]
        assert answer.json()["input_file"]["compressed"] is True
        assert wait_job(client, job, ("successful", "failed"))["status"] == "successful"

        cloud = client.get(f"/jobs/{job}/results/cloud")
        assert cloud.headers["content-type"] == "application/vnd.laszip"
        (tmp_path / "out.laz").write_bytes(cloud.content)
        flags = np.asarray(laspy.read(tmp_path / "out.laz").outlier_flags)
        assert len(flags) == 3000 and set(spikes) <= set(np.flatnonzero(flags))

        las_copy = client.get(f"/jobs/{job}/results/cloud", params={"format": "las"})
        (tmp_path / "out.las").write_bytes(las_copy.content)
        assert laspy.read(tmp_path / "out.las").header.are_points_compressed is False
        np.testing.assert_array_equal(np.asarray(laspy.read(tmp_path / "out.las").outlier_flags),
                                      flags)

        for keep, expected in (("inliers", flags == 0), ("outliers", flags != 0)):
            part = client.get(f"/jobs/{job}/results/cloud", params={"keep": keep})
            assert part.status_code == 200, part.text
            (tmp_path / f"{keep}.laz").write_bytes(part.content)
            assert len(laspy.read(tmp_path / f"{keep}.laz").points) == int(expected.sum())


def test_las_in_laz_out_on_request(stack: Stack, key: str, las_file, tmp_path: Path) -> None:
    path, _ = las_file
    with stack.client(key) as client:
        job = client.post("/processes/patch/execution",
                          files={"file": ("scan.las", path.read_bytes())},
                          data={"inputs": '{"k": 30, "sigma": 0.01}'}).json()["jobID"]
        done = wait_job(client, job, ("successful", "failed"))
        assert done["status"] == "successful", done["message"]
        laz = client.get(f"/jobs/{job}/results/cloud", params={"format": "laz"})
        assert laz.headers["content-type"] == "application/vnd.laszip"
        (tmp_path / "out.laz").write_bytes(laz.content)
        las = laspy.read(tmp_path / "out.laz")
        assert las.header.are_points_compressed
        assert "patch_score" in las.point_format.extra_dimension_names


def test_upload_then_execute_by_href(stack: Stack, key: str, las_file) -> None:
    path, _ = las_file
    with stack.client(key) as client:
        up = client.post("/uploads", params={"name": "scan.las"}, content=path.read_bytes())
        assert up.status_code == 201, up.text
        href = up.json()["href"]
        assert up.headers["location"] == href
        body = {"inputs": {"cloud": {"href": href}, "pipeline": [
            {"detector": "temporal", "sigma": 0.01}, {"detector": "section"}]}}
        answer = client.post("/processes/pipeline/execution", json=body)
        assert answer.status_code == 201, answer.text
        doc = answer.json()
        assert [s["detector"] for s in doc["inputs"]["pipeline"]] == ["temporal", "section"]
        done = wait_job(client, doc["jobID"], ("successful", "failed"))
        assert done["status"] == "successful", done["message"]
        # the upload serves a second job too
        again = client.post("/processes/temporal/execution",
                            json={"inputs": {"cloud": {"href": href}}})
        assert again.status_code == 201, again.text

        listing = client.get("/jobs", params={"limit": 2}).json()
        assert listing["jobs"][0]["jobID"] == again.json()["jobID"]  # newest first
        assert listing["numberReturned"] == 2
        assert any(link["rel"] == "next" for link in listing["links"])


def test_failed_job_reports_message(stack: Stack, key: str, tmp_path: Path) -> None:
    path = tmp_path / "no_time.las"
    untimed_cloud(path)
    with stack.client(key) as client:
        job = client.post("/processes/temporal/execution",
                          files={"file": ("no_time.las", path.read_bytes())}).json()["jobID"]
        done = wait_job(client, job, ("successful", "failed"))
        assert done["status"] == "failed"
        assert "gps_time" in done["message"]
        res = client.get(f"/jobs/{job}/results/cloud")
        assert res.status_code == 404
        assert res.headers["content-type"] == "application/problem+json"


def test_health_sees_the_worker(stack: Stack) -> None:
    with stack.client() as client:  # without a key: how many workers, not their host names
        health = client.get("/health")
        assert health.status_code == 200, health.text
        assert health.json()["redis"] == "ok" and health.json()["workers"] == 1
    with stack.client(stack.add_user("health-reader")) as client:
        assert len(client.get("/health").json()["workers"]) == 1
