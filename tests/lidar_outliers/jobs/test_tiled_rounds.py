"""A tiled job's rounds over the whole file (estimates fixed in several rounds): each round's
tasks are named by its number, so a message delivered again after its round was fixed (a worker
lost after finishing, Redis giving the task back) does nothing instead of failing the job."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from lidar_outliers.jobs.settings import Settings
from lidar_outliers.jobs.storage import open_storage
from lidar_outliers.jobs.store import JobStatus, Store
from lidar_outliers.jobs.tiles import pending_phase, pin_job_stage, run_job_tile, split_job
from tests.lasfiles import airborne_scene

#: detached scaled to the small scene: its spacings and voxel size are fixed in rounds
DETACHED = {"detector": "detached", "piece_points": 200, "k_floor": 16, "k_surface": 32}


@pytest.fixture
def settings(tmp_path: Path, database_url: str) -> Settings:
    return Settings(data_dir=tmp_path / "data", database_url=database_url, tile_job_points=1000,
                    tile_size=8.0)


def test_a_round_delivered_again_after_it_was_fixed_does_nothing(settings: Settings,
                                                                 store: Store,
                                                                 tmp_path: Path) -> None:
    storage = open_storage(settings)
    user, _ = store.add_user(f"u{os.urandom(4).hex()}")
    job = store.create_job(user.id, "detect", {"pipeline": [DETACHED]}, {"points": 4147}, False,
                           100)
    assert store.transition(job.id, JobStatus.running, "reading", worker_pid=os.getpid(),
                            worker_host="here") is not None
    source = airborne_scene(tmp_path / "airborne.las")
    cells = split_job(settings, store, storage, job.id, source, tmp_path / "split",
                      lambda *_: None)
    assert cells

    rounds = []
    while (pending := pending_phase(storage, job.id))[0] is not None:
        stage, _, round_ = pending
        assert round_ == len(rounds)
        assert all(run_job_tile(settings, store, storage, job.id, c, stage, round_)
                   for c in cells)
        assert pin_job_stage(settings, store, storage, job.id, stage, round_)
        # the same round's messages again: nothing to do, the job carries on
        assert not pin_job_stage(settings, store, storage, job.id, stage, round_)
        assert not run_job_tile(settings, store, storage, job.id, cells[0], stage, round_)
        rounds.append(stage)
    assert len(rounds) >= 2 and set(rounds) == {0}  # detached estimates in several rounds
    assert all(run_job_tile(settings, store, storage, job.id, c) for c in cells)
    stored = store.get_job(job.id)
    assert stored is not None and stored.status is JobStatus.running


def test_a_worker_keeps_the_halos_of_its_latest_rounds_only() -> None:
    from lidar_outliers.jobs import tiles

    for job in range(3 * tiles.HALO_MEMOS_KEPT):
        tiles._halo_memo((f"job-{job}", None, 0)).halos = [float(job)]
    assert len(tiles._HALO_MEMOS) == tiles.HALO_MEMOS_KEPT
    last = f"job-{3 * tiles.HALO_MEMOS_KEPT - 1}"
    assert tiles._halo_memo((last, None, 0)).halos == [3.0 * tiles.HALO_MEMOS_KEPT - 1]
    assert tiles._halo_memo(("job-0", None, 0)).halos is None  # forgotten: starts afresh
