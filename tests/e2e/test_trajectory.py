"""End to end: a job with a trajectory part beside the cloud runs the default mobile pipeline
with free-space evidence; a bad trajectory is a 422 problem and nothing is kept."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import pytest

from lidar_outliers.tools.simulator import simulate, write_simulation
from tests.e2e.stack import RedisServer, Stack, running_stack, wait_job


@pytest.fixture(scope="module")
def stack(redis_server: RedisServer, tmp_path_factory: pytest.TempPathFactory,
          compiled_detectors: None) -> Iterator[Stack]:
    with running_stack(tmp_path_factory.mktemp("data"), redis_server.new_url()) as s:
        yield s


@pytest.fixture(scope="module")
def key(stack: Stack) -> str:
    return stack.add_user("trajectory-user")


@pytest.fixture(scope="module")
def survey(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """Condition A at scale 0.01 (about 10 k points) and its trajectory file."""
    las = write_simulation(simulate("A", 3, 0.01), tmp_path_factory.mktemp("sim"))
    return las, las.with_suffix(".trajectory.txt")


def _parts(las: Path, trajectory: bytes | None, inputs: dict | None = None) -> dict:
    files = {"file": (las.name, las.read_bytes(), "application/octet-stream")}
    if trajectory is not None:
        files["trajectory"] = ("drive.txt", trajectory, "text/plain")
    if inputs is not None:
        files["inputs"] = (None, json.dumps(inputs).encode(), "application/json")
    return files


def test_upload_with_trajectory_part(stack: Stack, key: str, survey) -> None:
    las, traj = survey
    with stack.client(key) as client:
        answer = client.post("/processes/pipeline/execution",
                             files=_parts(las, traj.read_bytes()))
        assert answer.status_code == 201, answer.text
        doc = answer.json()
        assert doc["input_file"]["trajectory"]["name"] == "drive.txt"
        assert doc["input_file"]["trajectory"]["samples"] > 100
        done = wait_job(client, doc["jobID"], ("successful", "failed"))
        assert done["status"] == "successful", done["message"]
        stats = client.get(f"/jobs/{doc['jobID']}/results/statistics").json()
    assert stats["profile"] == "mobile" and stats["pipeline_source"] == "default"
    assert [s["detector"] for s in stats["stages"]] == ["transient", "height_field"]
    assert stats["trajectory"]["used_by"] == "transient"
    assert stats["trajectory"]["name"] == "drive.txt"
    info = stats["stages"][0]["info"]
    assert info["points_flagged_by_free_space"] > 0
    assert info["free_space"]["points_covered"] == stats["overall"]["points"]


def test_bad_trajectory_is_a_422_problem(stack: Stack, key: str, survey) -> None:
    las, _ = survey
    incoming = stack.data_dir / "uploads" / "incoming"
    with stack.client(key) as client:
        answer = client.post("/processes/pipeline/execution",
                             files=_parts(las, b"time x y z\n1 2 3 4\n0 2 3 4\n"))
        assert answer.status_code == 422, answer.text
        problem = answer.json()
        assert answer.headers["content-type"].startswith("application/problem+json")
        assert "drive.txt line 3" in problem["detail"] and "increase" in problem["detail"]
        assert problem["errors"][0]["parameter"] == "trajectory"
        # a trajectory named in the JSON inputs is refused with a pointer to the part
        answer = client.post("/processes/pipeline/execution",
                             files=_parts(las, None, {"trajectory": {"href": "/x"}}))
        assert answer.status_code == 422 and "multipart part `trajectory`" in answer.text
    assert not incoming.exists() or not list(incoming.glob("*.part"))


def test_json_request_with_uploaded_trajectory(stack: Stack, key: str, survey) -> None:
    las, traj = survey
    with stack.client(key) as client:
        cloud = client.post("/uploads", params={"name": las.name}, content=las.read_bytes())
        assert cloud.status_code == 201, cloud.text
        path = client.post("/uploads", params={"name": "drive.txt", "kind": "trajectory"},
                           content=traj.read_bytes())
        assert path.status_code == 201, path.text
        # a LAS file is not a trajectory, nor a trajectory a cloud
        wrong = client.post("/uploads", params={"kind": "trajectory"}, content=las.read_bytes())
        assert wrong.status_code == 422 and "not a text file" in wrong.json()["detail"]
        answer = client.post("/processes/pipeline/execution", json={"inputs": {
            "cloud": {"href": path.json()["href"]}}})
        assert answer.status_code == 415, answer.text
        answer = client.post("/processes/pipeline/execution", json={"inputs": {
            "cloud": {"href": cloud.json()["href"]}, "trajectory": {"href": "/uploads/nope"}}})
        assert answer.status_code == 422 and "trajectory.href" in answer.text
        answer = client.post("/processes/pipeline/execution", json={"inputs": {
            "cloud": {"href": cloud.json()["href"]},
            "trajectory": {"href": path.json()["href"]}}})
        assert answer.status_code == 201, answer.text
        done = wait_job(client, answer.json()["jobID"], ("successful", "failed"))
        assert done["status"] == "successful", done["message"]
        assert done["input_file"]["trajectory"]["name"] == "drive.txt"
        stats = client.get(f"/jobs/{done['jobID']}/results/statistics").json()
    assert stats["trajectory"]["used_by"] == "transient"
    assert stats["stages"][0]["info"]["points_flagged_by_free_space"] > 0
