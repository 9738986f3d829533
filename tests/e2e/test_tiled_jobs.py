"""One job over two workers: a job of more than TILE_JOB_POINTS points is cut into tiles that
both worker processes run, merged in the input's order: the same result as one machine. A
corrupt tile fails the job with the tile's message and leaves nothing of a result. The workers
beat and sweep every second and take a job without a heartbeat for 5 s for a dead worker's: no
process holds a job while its tiles run, yet none is queued again."""

from __future__ import annotations

import json
import os
import re
import signal
from collections.abc import Iterator
from pathlib import Path

import laspy
import numpy as np
import pytest

from lidar_outliers.jobs.store import Store
from lidar_outliers.process import process_file
from tests.e2e.stack import RedisServer, Stack, alive, running_stack, wait_for, wait_job
from tests.lasfiles import STREET_TRANSIENT, scanned_tile_scene, street_scene, tile_scene

SENSOR = [600_012.0, 5_000_012.0, 52.0]
PIPELINE = {"pipeline": [{"detector": "dror", "origin": SENSOR, "multiplier": 8.0},
                         {"detector": "section", "section_size": 2.0},
                         {"detector": "patch", "k": 30}]}


@pytest.fixture(scope="module")
def stack(redis_server: RedisServer, tmp_path_factory: pytest.TempPathFactory,
          compiled_detectors: None) -> Iterator[Stack]:
    # quick heartbeats and sweeps (as in test_workers): a tiled job is not taken for a dead
    # worker's while no process holds it
    with running_stack(tmp_path_factory.mktemp("data"), redis_server.new_url(), workers=2,
                       tile_job_points=2000, tile_size=3.0, task_time_limit=300,
                       visibility_timeout=320, heartbeat_interval_seconds=1,
                       stale_job_seconds=5) as s:
        yield s


@pytest.fixture(scope="module")
def key(stack: Stack) -> str:
    return stack.add_user("tiler")


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tile_scene(tmp_path_factory.mktemp("in") / "scene.las")


#: dror, then height_field with sigma estimated from the whole cloud: a round of tiles
#: gathers the residuals, one task fixes sigma, a second round runs the pipeline.
ESTIMATED = {"pipeline": [{"detector": "dror", "origin": SENSOR, "multiplier": 8.0},
                          {"detector": "height_field", "low": False}]}


def submit(stack: Stack, key: str, path: Path, inputs: dict | None = None) -> str:
    with stack.client(key) as client:
        answer = client.post("/processes/pipeline/execution",
                             files={"file": (path.name, path.read_bytes())},
                             data={"inputs": json.dumps(inputs or PIPELINE)})
        assert answer.status_code == 201, answer.text
        return answer.json()["jobID"]


def requeues(stack: Stack, job: str) -> int:
    record = Store(stack.data_dir / "service.sqlite3", migrate=False).get_job(job)
    assert record is not None
    return record.requeues


def tile_runs(stack: Stack) -> list[int]:
    """Tile tasks each worker finished, from their logs."""
    return [log.read_text().count("lidar_outliers.run_tile[") for log in
            sorted(stack.logs.glob("worker*.log"))]


def finished(stack: Stack, key: str, job: str, out: Path) -> tuple[Path, dict]:
    """Wait for a successful job; its cloud written to ``out`` and its statistics."""
    with stack.client(key) as client:
        done = wait_job(client, job, ("successful", "failed"), timeout=300)
        assert done["status"] == "successful", done["message"]
        out.write_bytes(client.get(f"/jobs/{job}/results/cloud").content)
        return out, client.get(f"/jobs/{job}/results/statistics").json()


def assert_same_scores(a: laspy.LasData, b: laspy.LasData, names: list[str]) -> None:
    """The detectors' scores agree within float tolerance, NaN (untested) in the same places."""
    for name in names:
        x, y = np.asarray(a[f"{name}_score"]), np.asarray(b[f"{name}_score"])
        assert np.array_equal(np.isnan(x), np.isnan(y))
        np.testing.assert_allclose(x[~np.isnan(x)], y[~np.isnan(y)], rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("inputs", [PIPELINE, ESTIMATED], ids=["tiles", "estimate first"])
def test_tiles_over_two_workers_give_the_one_machine_result(stack, key, scene, tmp_path, inputs):
    job = submit(stack, key, scene, inputs)
    out, stats = finished(stack, key, job, tmp_path / "service.las")
    assert stats["mode"] == "tiled over workers"
    assert stats["tiles"]["count"] >= 60 and stats["input"]["name"] == "scene.las"
    assert all(runs > 0 for runs in tile_runs(stack)), tile_runs(stack)  # both took part
    local = tmp_path / "local.las"
    local_stats = process_file(scene, local, inputs)
    assert local_stats["mode"] == "in memory"
    a, b = laspy.read(local), laspy.read(out)
    assert (a.outlier_flags != 0).any()
    assert np.array_equal(a.outlier_flags, b.outlier_flags)
    assert np.array_equal(a.classification, b.classification)
    assert_same_scores(a, b, [s["detector"] for s in inputs["pipeline"]])
    assert stats["overall"] == local_stats["overall"]
    for remote, here in zip(stats["stages"], local_stats["stages"], strict=True):
        assert remote["params"] == here["params"]
        if "sigma_source" in here["info"]:
            assert remote["info"]["sigma"] == pytest.approx(here["info"]["sigma"], rel=1e-9)
    assert not (stack.data_dir / "jobs" / job / "tiles").exists()
    assert requeues(stack, job) == 0


#: temporal first (its scan lines cross every tile), then height_field with sigma estimated
#: over what temporal left: temporal is streamed by the worker that cuts the tiles, a round of
#: tiles estimates sigma, a second round runs height_field.
STREAMED = {"pipeline": [{"detector": "temporal", "max_gap": 0.001},
                         {"detector": "height_field", "low": False}]}


def test_temporal_first_streams_then_tiles_give_the_one_machine_result(stack, key, tmp_path):
    scanned = scanned_tile_scene(tmp_path / "scanned.las", shuffled=True)
    job = submit(stack, key, scanned, STREAMED)
    out, stats = finished(stack, key, job, tmp_path / "service.las")
    assert stats["mode"] == "tiled over workers" and stats["streamed"]["stages"] == ["temporal"]
    local = tmp_path / "local.las"
    local_stats = process_file(scanned, local, STREAMED)
    a, b = laspy.read(local), laspy.read(out)
    assert np.array_equal(a.outlier_flags, b.outlier_flags)
    assert_same_scores(a, b, ["temporal", "height_field"])
    assert stats["overall"] == local_stats["overall"]
    for remote, here in zip(stats["stages"], local_stats["stages"], strict=True):
        assert here["points_flagged"] > 0
        assert (remote["points_in"], remote["points_tested"], remote["points_flagged"]) == (
            here["points_in"], here["points_tested"], here["points_flagged"])
    assert stats["stages"][0]["info"] == local_stats["stages"][0]["info"]
    assert stats["stages"][1]["info"]["sigma"] == pytest.approx(
        local_stats["stages"][1]["info"]["sigma"], rel=1e-9)
    assert not (stack.data_dir / "jobs" / job / "tiles").exists()


def test_temporal_alone_runs_on_one_worker_without_tiles(stack, key, tmp_path):
    # temporal alone follows the scan lines over the whole file in bounded memory: cutting
    # tiles for it would only add work.
    scanned = scanned_tile_scene(tmp_path / "scanned.las")
    inputs = {"pipeline": [{"detector": "temporal", "max_gap": 0.001}]}
    before = sum(tile_runs(stack))
    job = submit(stack, key, scanned, inputs)
    out, stats = finished(stack, key, job, tmp_path / "service.las")
    assert stats["mode"] == "in memory" and "tiling" not in stats
    assert sum(tile_runs(stack)) == before
    local = tmp_path / "local.las"
    process_file(scanned, local, inputs)
    a, b = laspy.read(local), laspy.read(out)
    assert np.array_equal(a.outlier_flags, b.outlier_flags) and np.sum(a.outlier_flags) > 0
    assert not (stack.data_dir / "jobs" / job / "tiles").exists()


@pytest.mark.parametrize("inputs", [
    {"pipeline": [STREET_TRANSIENT]},
    {"pipeline": [{"detector": "temporal", "max_gap": 0.001}, STREET_TRANSIENT,
                  {"detector": "height_field"}]},
], ids=["transient", "temporal, transient, height_field estimated"])
def test_transient_job_tiles_after_its_pass_over_the_whole_file(stack, key, tmp_path, inputs):
    """transient's persistence and scan-line neighbours come from a round of tiles and one
    combining task, then the tiles run: the one machine's result. After temporal (streamed)
    and before height_field's estimates, transient's results are kept from the round that
    estimates (settled) and the later rounds run on the points it left."""
    street = street_scene(tmp_path / "street.las")
    job = submit(stack, key, street, inputs)
    out, stats = finished(stack, key, job, tmp_path / "service.las")
    assert stats["mode"] == "tiled over workers"
    transient = next(s for s in stats["stages"] if s["detector"] == "transient")
    assert transient["info"]["scan_lines"].startswith("in file order")
    local = tmp_path / "local.las"
    local_stats = process_file(street, local, inputs)
    a, b = laspy.read(local), laspy.read(out)
    assert ((np.asarray(a.outlier_flags) & 128) != 0).any()
    assert np.array_equal(a.outlier_flags, b.outlier_flags)
    assert_same_scores(a, b, [s["detector"] for s in inputs["pipeline"]])
    assert stats["overall"] == local_stats["overall"]
    for remote, here in zip(stats["stages"], local_stats["stages"], strict=True):
        assert (remote["points_in"], remote["points_tested"], remote["points_flagged"]) == (
            here["points_in"], here["points_tested"], here["points_flagged"])
    assert not (stack.data_dir / "jobs" / job / "tiles").exists()
    assert requeues(stack, job) == 0


def test_a_corrupt_tile_fails_the_job_with_its_message(stack, key, scene):
    job = submit(stack, key, scene)
    tiles = stack.data_dir / "jobs" / job / "tiles"
    wait_for(lambda: (tiles / "tiles.json").exists(), 120, "the job's tiles", interval=0.02)
    for cell in tiles.glob("cell_*.bin"):
        with open(cell, "ab") as fh:
            fh.write(b"not a point")
    with stack.client(key) as client:
        done = wait_job(client, job, ("successful", "failed"), timeout=300)
    assert done["status"] == "failed"
    assert "tile file cell_" in done["message"] and "expected" in done["message"], done["message"]
    # the chord's error callback ran: no tiles, no result, no statistics are left
    wait_for(lambda: not tiles.exists(), 120, "the tiles to be removed")
    assert not [p.name for p in (stack.data_dir / "jobs" / job).glob("result*")]
    assert not (stack.data_dir / "jobs" / job / "statistics.json").exists()
    with stack.client(key) as client:
        assert client.get(f"/jobs/{job}").json()["status"] == "failed"
    # the workers are free again: the next job runs to the end
    again = submit(stack, key, scene)
    with stack.client(key) as client:
        assert wait_job(client, again, ("successful", "failed"), timeout=300)["status"] == (
            "successful")


def test_a_tile_whose_worker_is_killed_is_run_again_and_only_it(stack, key, scene, tmp_path):
    before = [log.read_text() for log in sorted(stack.logs.glob("worker*.log"))]
    job = submit(stack, key, scene)
    scratch = stack.data_dir / "scratch"

    def tile_process() -> int | None:
        """The pid of a process running one of the job's tiles (its scratch folder's name)."""
        for folder in scratch.glob(f"tile-{job}-*"):
            pid = int(folder.name.rsplit("-", 2)[1])
            if pid in alive([pid]):
                return pid
        return None

    victim = wait_for(tile_process, 120, "a tile to run", interval=0.01)
    os.kill(victim, signal.SIGKILL)
    with stack.client(key) as client:
        done = wait_job(client, job, ("successful", "failed"), timeout=300)
        assert done["status"] == "successful", done["message"]
        out = tmp_path / "service.las"
        out.write_bytes(client.get(f"/jobs/{job}/results/cloud").content)
        count = client.get(f"/jobs/{job}/results/statistics").json()["tiles"]["count"]
    logs = [log.read_text()[len(old):] for log, old in
            zip(sorted(stack.logs.glob("worker*.log")), before, strict=True)]
    received, succeeded = (
        sum(len(re.findall(rf"lidar_outliers\.run_tile\[[^\]]+\] {what}", text)) for text in logs)
        for what in ("received", "succeeded"))
    assert succeeded == count
    assert received == count + 1  # the killed tile twice, every other tile once
    assert requeues(stack, job) == 0
    local = tmp_path / "local.las"
    process_file(scene, local, PIPELINE)
    assert np.array_equal(laspy.read(local).outlier_flags, laspy.read(out).outlier_flags)
