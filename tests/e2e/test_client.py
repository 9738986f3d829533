"""The Python client and `lidar-outliers submit` against the real stack (API, Redis, a worker)."""

from __future__ import annotations

import io
import json
import os
import re
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import laspy
import numpy as np
import pytest

from lidar_outliers import view
from lidar_outliers.client import Client, ServiceError
from lidar_outliers.tools.simulator import simulate, write_simulation
from tests.e2e.stack import ROOT, RedisServer, Stack, free_port, running_stack
from tests.lasfiles import untimed_cloud, write_cloud

CLI = str(Path(sys.executable).parent / "lidar-outliers")


@pytest.fixture(scope="module")
def stack(redis_server: RedisServer, tmp_path_factory: pytest.TempPathFactory,
          compiled_detectors: None) -> Iterator[Stack]:
    with running_stack(tmp_path_factory.mktemp("data"), redis_server.new_url(),
                       max_active_jobs_per_user=8) as s:
        yield s


@pytest.fixture(scope="module")
def key(stack: Stack) -> str:
    return stack.add_user("client-user")


@pytest.fixture(scope="module")
def las_file(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, np.ndarray]:
    path = tmp_path_factory.mktemp("in") / "scan.las"
    return path, write_cloud(path, n=4000, seed=5)


def submit_cli(stack: Stack, key: str | None, *args: str, cwd: Path) -> subprocess.CompletedProcess:
    """`lidar-outliers submit ARGS` as a user runs it, server and key from the environment."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("LIDAR_OUTLIERS_")}
    env["LIDAR_OUTLIERS_SERVER"] = stack.url
    env["PYTHONPATH"] = str(ROOT)  # this checkout's client, whichever one the venv came from
    if key is not None:
        env["LIDAR_OUTLIERS_KEY"] = key
    return subprocess.run([CLI, "submit", *args], env=env, cwd=cwd, capture_output=True,
                          text=True, timeout=300)


def test_submit_wait_download_is_what_the_api_serves(stack: Stack, key: str, las_file,
                                                     tmp_path: Path) -> None:
    path, spikes = las_file
    seen: list[dict] = []
    with Client(stack.url, key) as api, stack.client(key) as http:
        sent: list[tuple[int, int]] = []
        job = api.submit(path, "temporal", {"sigma": 0.01},
                         progress=lambda done, total: sent.append((done, total)))
        assert job["status"] in ("accepted", "running") and job["processID"] == "temporal"
        assert sent[-1] == (path.stat().st_size, path.stat().st_size)
        done = api.wait(job["jobID"], seen.append, timeout=180)
        assert done["status"] == "successful" and done["progress"] == 100
        assert seen[-1] == done and all(0 <= d["progress"] <= 100 for d in seen)

        out = api.download(job["jobID"], tmp_path / "flagged.las")
        served = http.get(f"/jobs/{job['jobID']}/results/cloud")
        assert out.read_bytes() == served.content
        flags = np.asarray(laspy.read(out).outlier_flags)
        assert set(spikes) <= set(np.flatnonzero(flags))
        assert [p.name for p in tmp_path.iterdir()] == ["flagged.las"]  # no partial file left

        laz = api.download(job["jobID"], tmp_path / "outliers.laz", keep="outliers")
        served = http.get(f"/jobs/{job['jobID']}/results/cloud",
                          params={"keep": "outliers", "format": "laz"})
        assert laz.read_bytes() == served.content
        assert laspy.read(laz).header.point_count == np.count_nonzero(flags)

        stats = api.statistics(job["jobID"])
        assert stats == http.get(f"/jobs/{job['jobID']}/results/statistics").json()
        assert stats["overall"]["points_flagged"] == np.count_nonzero(flags)
        assert job["jobID"] in [j["jobID"] for j in api.jobs()]

        points = http.get(f"/jobs/{job['jobID']}/results/points", params={"max_points": 1000})
        assert points.headers["content-type"] == view.MEDIA_TYPE
        header, xyz, got = view.parse(points.content)
        assert header["points"] == 1000 and header["total"] == 4000
        assert np.count_nonzero(got) == np.count_nonzero(flags)  # every outlier is drawn

        assert api.dismiss(job["jobID"])["status"] == "dismissed"
        with pytest.raises(ServiceError) as gone:
            api.download(job["jobID"], tmp_path / "again.las")
        assert gone.value.status == 404 and gone.value.title == "Unknown job"
        assert not (tmp_path / "again.las").exists()


def test_upload_then_submit_by_href_with_a_trajectory(stack: Stack, key: str,
                                                      tmp_path: Path) -> None:
    las = write_simulation(simulate("A", 3, 0.01), tmp_path)
    trajectory = las.with_suffix(".trajectory.txt")
    with Client(stack.url, key) as api:
        upload = api.upload(las)
        assert upload["href"].startswith("/uploads/") and upload["bytes"] == las.stat().st_size
        by_href = api.submit(upload["href"], trajectory=trajectory)
        by_file = api.submit(las, trajectory=trajectory)
        for job in (by_href, by_file):
            assert job["input_file"]["trajectory"]["name"] == trajectory.name
            assert api.dismiss(job["jobID"])["status"] == "dismissed"


def test_readme_client_example_runs(stack: Stack, key: str, las_file, tmp_path: Path,
                                    monkeypatch: pytest.MonkeyPatch,
                                    capsys: pytest.CaptureFixture[str]) -> None:
    readme = (ROOT / "README.md").read_text()
    blocks = re.findall(r"^```python\n(.*?)^```", readme, flags=re.MULTILINE | re.DOTALL)
    code = next(block for block in blocks if "lidar_outliers.client" in block)
    assert '"http://127.0.0.1:8000"' in code
    shutil.copy(las_file[0], tmp_path / "scan.las")
    monkeypatch.chdir(tmp_path)
    exec(compile(code.replace('"http://127.0.0.1:8000"', repr(stack.url)), "README.md", "exec"),
         {"key": key})
    assert capsys.readouterr().out.splitlines()[-1] == "100 %"
    assert laspy.read(tmp_path / "flagged.laz").header.are_points_compressed


def test_cli_submit_downloads_result_and_statistics(stack: Stack, key: str, las_file,
                                                    tmp_path: Path) -> None:
    path, spikes = las_file
    answer = submit_cli(stack, key, str(path), "--detector", "temporal", "--sigma", "0.01",
                        "--detector", "section", "-o", "flagged.laz", "--stats", "stats.json",
                        cwd=tmp_path)
    assert answer.returncode == 0, answer.stderr
    assert answer.stdout == "" and answer.stderr == ""  # quiet when not on a terminal
    stats = json.loads((tmp_path / "stats.json").read_text())
    assert [s["detector"] for s in stats["stages"]] == ["temporal", "section"]
    assert stats["stages"][0]["params"]["sigma"] == 0.01
    with Client(stack.url, key) as api, stack.client(key) as http:
        job = api.jobs()[0]
        assert job["status"] == "successful"
        served = http.get(f"/jobs/{job['jobID']}/results/cloud", params={"format": "laz"})
        assert (tmp_path / "flagged.laz").read_bytes() == served.content
        assert stats == api.statistics(job["jobID"])
    flags = np.asarray(laspy.read(tmp_path / "flagged.laz").outlier_flags)
    assert set(spikes) <= set(np.flatnonzero(flags))

    # statistics on stdout without --stats; the default output name beside the input's
    answer = submit_cli(stack, key, str(path), "--process", "temporal", "--params",
                        '{"sigma": 0.01}', cwd=tmp_path)
    assert answer.returncode == 0, answer.stderr
    assert json.loads(answer.stdout)["stages"][0]["detector"] == "temporal"
    assert laspy.read(tmp_path / "scan.flagged.las").header.point_count == 4000


def test_cli_failed_job_exits_with_its_message(stack: Stack, key: str, tmp_path: Path) -> None:
    no_time = tmp_path / "no_time.las"
    untimed_cloud(no_time)
    answer = submit_cli(stack, key, str(no_time), "--detector", "temporal", "-o", "out.las",
                        cwd=tmp_path)
    assert answer.returncode == 1
    lines = answer.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("lidar-outliers: error: Job failed: job ")
    assert "gps_time" in lines[0]
    assert not (tmp_path / "out.las").exists()


def test_laz_of_a_waveform_result_is_a_422_problem(stack: Stack, key: str,
                                                   tmp_path: Path) -> None:
    # lazrs would change the waveform fields of point format 10: the LAS result is served, a
    # LAZ one is refused with a problem that says why, and the connection stays usable
    wave = tmp_path / "wave.las"
    write_cloud(wave, n=500, point_format=10)
    with Client(stack.url, key) as api, stack.client(key) as http:
        job = api.submit(wave, inputs={"pipeline": [{"detector": "temporal", "sigma": 0.01}]})
        job = job["jobID"]
        assert api.wait(job)["status"] == "successful"
        url = f"/jobs/{job}/results/cloud"
        for params in ({"format": "laz"}, {"format": "laz", "keep": "inliers"}):
            answer = http.get(url, params=params)
            assert answer.status_code == 422, answer.text
            assert answer.headers["content-type"] == "application/problem+json"
            assert answer.json()["type"].endswith("/unsupported-output")
            assert "point format 10" in answer.json()["detail"]
        served = http.get(url, params={"keep": "inliers"})
        assert served.status_code == 200
        assert laspy.read(io.BytesIO(served.content)).header.point_format.id == 10


def test_cli_wrong_key_gives_the_401_problem(stack: Stack, las_file, tmp_path: Path) -> None:
    path, _ = las_file
    answer = submit_cli(stack, "not-a-key", str(path), cwd=tmp_path)
    assert answer.returncode == 1
    assert answer.stderr == ("lidar-outliers: error: 401 Missing or wrong API key: the API key "
                             "is wrong or revoked\n")


def test_cli_refused_inputs_give_the_422_problem(stack: Stack, key: str, las_file,
                                                 tmp_path: Path) -> None:
    path, _ = las_file
    answer = submit_cli(stack, key, str(path), "--process", "temporal", "--params",
                        '{"n1": 0}', cwd=tmp_path)
    assert answer.returncode == 1
    assert answer.stderr.startswith("lidar-outliers: error: 422 Invalid parameter: n1: ")
    assert len(answer.stderr.splitlines()) == 1


def test_cli_checks_parameters_before_sending(las_file, tmp_path: Path) -> None:
    path, _ = las_file
    nowhere = Stack.__new__(Stack)
    nowhere.port = free_port()  # nothing listens: the command must not get that far
    answer = submit_cli(nowhere, "k", str(path), "--detector", "temporal", "--n1", "0",
                        cwd=tmp_path)
    assert answer.returncode == 2
    assert answer.stderr.startswith("lidar-outliers: error: --n1 of --detector temporal: ")
    answer = submit_cli(nowhere, "k", str(path), cwd=tmp_path)
    assert answer.returncode == 1
    assert answer.stderr.startswith("lidar-outliers: error: Service unreachable: "
                                    f"http://127.0.0.1:{nowhere.port}: ")
    env = {k: v for k, v in os.environ.items() if not k.startswith("LIDAR_OUTLIERS_")}
    answer = subprocess.run([CLI, "submit", str(path)], env=env, cwd=ROOT, capture_output=True,
                            text=True, timeout=60)
    assert answer.returncode == 2
    assert answer.stderr == ("lidar-outliers: error: --server is required (or set "
                             "LIDAR_OUTLIERS_SERVER)\n")
