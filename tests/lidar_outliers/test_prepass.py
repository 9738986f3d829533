"""A streamed stage over a whole file == the same stage on the cloud in memory: any record
order, 'auto' sigma and max_gap resolved over the whole series, in bounded memory."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from lidar_outliers import lasio
from lidar_outliers.params import PipelineParams
from lidar_outliers.pipeline import jsonable, run_pipeline
from lidar_outliers.prepass import STEP_DTYPE, middle_values, run_streamed
from tests.lasfiles import scan_line_cloud, write_las


@pytest.fixture(scope="module")
def crowded(tmp_path_factory) -> Path:
    """Two scanners, 110,000 points (more tested points than the sigma estimate samples),
    nine in ten of them within one second of a 20 s drive, a few without a time, the records
    shuffled: sorting on disk splits the crowded second again."""
    rng = np.random.default_rng(11)
    n = 110_000
    xyz, _, _ = scan_line_cloud(n, rng, spikes=200)
    t = np.sort(np.r_[rng.uniform(0, 20, n // 10), rng.uniform(8, 9, n - n // 10)])
    t[rng.choice(n, 30, replace=False)] = np.nan
    group = np.where(np.arange(n) % 3 == 0, 2, 1).astype(np.uint16)
    order = rng.permutation(n)
    return write_las(tmp_path_factory.mktemp("crowded") / "crowded.las",
                     xyz[order] + [500_000, 5_000_000, 100], gps_time=t[order] + 1e5,
                     point_source_id=group[order], offsets=(500_000, 5_000_000, 0), vlrs=())


@pytest.mark.parametrize("stage", [{"detector": "temporal"},
                                   {"detector": "temporal", "sigma": 0.003, "max_gap": 0.01,
                                    "group_by": "none"}])
def test_streamed_temporal_is_the_whole_clouds(crowded, tmp_path, stage):
    params = PipelineParams.model_validate({"pipeline": [stage]})
    whole = run_pipeline(lasio.read_cloud(crowded), params)
    said: list[tuple[float, str]] = []
    out = run_streamed(crowded, list(params.pipeline), len(whole.flags), tmp_path / "s",
                       chunk_points=5_000, progress=lambda f, m: said.append((f, m)))
    assert {f for f, _ in said} == {0.1}
    assert "temporal along time: sorting by time, 110,000 of 110,000 points" in {
        m for _, m in said}
    assert np.array_equal(out.flags, whole.flags) and whole.flags.any()
    assert np.array_equal(out.scores["temporal"], whole.scores["temporal"], equal_nan=True)
    info = whole.statistics["stages"][0]["info"]
    assert jsonable(out.stages[0]["info"]) == info
    assert out.stages[0]["critical_value"] == whole.statistics["stages"][0]["critical_value"]
    assert not list((tmp_path / "s").glob("stage_*"))  # the sorted copies are gone


def test_middle_values_are_each_groups_median(tmp_path):
    rng = np.random.default_rng(2)
    steps = np.empty(5001, dtype=STEP_DTYPE)
    group = rng.integers(0, 3, steps.size)
    group[group == 1] = 0  # group 1 has no steps
    values = rng.exponential(1e-4, steps.size)
    values[:50] = values[50]  # repeated steps
    steps["group"], steps["bits"] = group, values.view(np.uint64)
    steps.tofile(tmp_path / "steps.bin")
    counts = np.bincount(group, minlength=3)
    got = middle_values(tmp_path / "steps.bin", counts, chunk_points=700)
    assert got[0] == np.median(values[group == 0]) and got[2] == np.median(values[group == 2])
    assert np.isnan(got[1])
