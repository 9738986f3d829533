"""`lidar-outliers plot` and `render_preview`: PNGs of the expected size from real result files."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest

from lidar_outliers.cli import main
from lidar_outliers.tools import plot
from tests.lasfiles import write_las

WIDTH, HEIGHT = int(plot.FIGSIZE[0] * plot.DPI), int(plot.FIGSIZE[1] * plot.DPI)


def _png_size(path) -> tuple[int, int]:
    head = path.read_bytes()[:24]
    assert head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR"
    return struct.unpack(">II", head[16:24])


@pytest.fixture
def result_file(tmp_path):
    """A small result LAS as the pipeline writes it: outlier_flags and two *_score dimensions."""
    rng = np.random.default_rng(5)
    n = 3000
    x, y = rng.uniform(0, 20, n), rng.uniform(-3, 3, n)
    truth = rng.random(n) < 0.02
    z = 0.01 * rng.normal(size=n) + np.where(truth, rng.uniform(0.2, 1.0, n), 0.0)
    temporal = np.abs(rng.normal(size=n)) + np.where(truth, 8.0, 0.0)
    patch = np.where(rng.random(n) < 0.1, np.nan, np.abs(rng.normal(size=n)))
    extra = {"outlier_flags": np.where(temporal > 3.29, 1, 0).astype(np.uint16),
             "temporal_score": temporal.astype(np.float32),
             "patch_score": patch.astype(np.float32)}
    path = write_las(tmp_path / "cloud.result.las", np.column_stack([x, y, z]),
                     gps_time=np.arange(n) * 1e-5, point_format=6, extra=extra, vlrs=())
    np.savez(tmp_path / "cloud.truth.npz", is_outlier=truth)
    return path


def test_plot_command_with_truth_writes_png_of_expected_size(result_file, tmp_path):
    out = tmp_path / "view.png"
    assert main(["plot", str(result_file), "--truth", str(tmp_path / "cloud.truth.npz"),
                 "-o", str(out)]) == 0
    assert _png_size(out) == (WIDTH, HEIGHT)


def test_render_preview_without_truth(result_file, tmp_path):
    out = tmp_path / "preview.png"
    assert plot.render_preview(result_file, out) == out
    assert _png_size(out) == (WIDTH, HEIGHT)


def test_critical_values_come_from_statistics_beside_the_file(result_file, tmp_path):
    stats = {"stages": [{"detector": "temporal", "critical_value": 4.5},
                        {"detector": "patch", "critical_value": None}]}
    (tmp_path / "cloud.result.stats.json").write_text(json.dumps(stats))
    found = plot.find_statistics(result_file)
    crits = plot.critical_values(["temporal", "patch"], found)
    assert crits["temporal"] == (4.5, "statistics")
    # patch falls back to t(k - 9) at the default alpha: k = 40 gives t(31), 0.001 two-sided
    from scipy import stats as st

    assert crits["patch"][1] == "default params"
    assert crits["patch"][0] == pytest.approx(st.t.isf(0.0005, 31))


def test_categories_partition_the_points():
    flags = np.array([0, 1, 2, 0, 4], dtype=np.uint8)
    truth = np.array([False, True, False, True, True])
    cats = plot.categories(flags, truth)
    stacked = np.vstack(list(cats.values()))
    assert np.all(stacked.sum(axis=0) == 1)
    assert cats["true positive"].tolist() == [False, True, False, False, True]
    assert cats["miss"].tolist() == [False, False, False, True, False]
    assert cats["false alarm"].tolist() == [False, False, True, False, False]


def test_truth_of_wrong_length_is_one_line_error(result_file, tmp_path, capsys):
    np.savez(tmp_path / "short.npz", is_outlier=np.zeros(5, dtype=bool))
    with pytest.raises(SystemExit) as exc:
        main(["plot", str(result_file), "--truth", str(tmp_path / "short.npz"),
              "-o", str(tmp_path / "x.png")])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "3000 points" in err


def test_not_a_las_file_is_one_line_error(tmp_path, capsys):
    bad = tmp_path / "bad.las"
    bad.write_bytes(b"not a las file at all")
    with pytest.raises(SystemExit) as exc:
        main(["plot", str(bad), "-o", str(tmp_path / "x.png")])
    assert exc.value.code == 1
    assert capsys.readouterr().err.count("\n") == 1
