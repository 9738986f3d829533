"""`lidar-outliers bench --quick` end to end, the registry-driven pipelines, the paper data."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from lidar_outliers.cli import main
from lidar_outliers.detectors import DETECTORS, Detector
from lidar_outliers.tools import bench, paper
from tests.lasfiles import subset_las

DATA = Path(__file__).resolve().parents[2] / "data"


@pytest.fixture
def real_folders(tmp_path):
    """Small ISPRS and airborne folders cut from the real files in tests/data."""
    isprs = tmp_path / "isprs"
    isprs.mkdir()
    subset_las(DATA / "isprs" / "samp21.laz", isprs / "samp21.laz", 2500)
    airborne = tmp_path / "airborne"
    airborne.mkdir()
    index = subset_las(DATA / "airborne" / "laspy__append-bug.laz",
                       airborne / "cut.laz", 6000)
    with np.load(DATA / "airborne" / "laspy__append-bug.truth.npz") as t:
        np.savez(airborne / "cut.truth.npz", is_outlier=t["is_outlier"][index],
                 gross=t["gross"][index])
    return isprs, airborne


def test_quick_bench_writes_tables_with_the_command(real_folders, tmp_path):
    isprs, airborne = real_folders
    md, js = tmp_path / "bench.md", tmp_path / "bench.json"
    status = main(["bench", "--quick", "--scale", "0.03", "--cache", str(tmp_path / "cache"),
                   "--isprs", str(isprs), "--wads", "none", "--airborne", str(airborne),
                   "--markdown", str(md), "--json", str(js)])
    assert status == 0
    text = md.read_text()
    assert text.splitlines()[2].startswith("Command: `lidar-outliers bench --quick --scale 0.03")
    # reported on seeds the detectors were not tuned on, and the report says which
    assert "tuned on seeds 0-2, reported on seeds 100." in text
    assert "### Systems of the reporting seeds" in text and "| 100 | " in text
    for name in bench.outlier_pipelines():
        assert f"### {name}" in text
    # the paper's published figures sit beside ours (Table 2, cloud A: 3,414 identified)
    assert "| No. of Outliers Identified | " in text and "3,414" in text
    assert "## ISPRS ground-filter samples" in text and "| samp21 | 2,500 |" in text
    assert "| **mean** |" in text
    assert "### Recall by outlier kind, per condition" in text and "exhaust_plume" in text
    assert "lowest kind recall %" in text
    untested = text.split("### Points the quadric fits left untested")[1].split("\n#")[0]
    assert "| patch | patch | A | " in untested and "| section | section | C | " in untested
    assert "did_not_converge %" in untested
    assert "## Real airborne tiles" in text and "| cut.laz | 6,000 | " in text
    assert "| airborne (" in text and "Targets met on " in text
    for name in DETECTORS:
        assert any(line.startswith(f"| {name} | ") for line in text.split("## Speed")[1]
                   .splitlines())
    numbers = json.loads(js.read_text())
    sim = numbers["simulated"]
    assert sim["tune_seeds"] == [0, 1, 2] and sim["report_seeds"] == [100]
    # pooled counts are consistent with the truth files of the cached clouds
    cached = sorted((tmp_path / "cache").rglob("*.truth.npz"))
    assert {p.name for p in cached} == {f"{c}_100.truth.npz" for c in "ABC"}
    by_cond = {p.name[0]: int(np.load(p)["is_outlier"].sum()) for p in cached}
    for name, per_cloud in sim["pipelines"].items():
        for cond, conf in per_cloud.items():
            assert conf["outliers"] == by_cond[cond], (name, cond)
            assert conf["outliers_identified"] + conf["outliers_missed"] == conf["outliers"]
            kinds = sim["kinds"][name][cond]
            assert sum(k["count"] for k in kinds.values()) == conf["outliers"]
            met = sim["targets"][name][cond]["met"]
            assert met == (conf["recall"] >= 0.9 and all(k["recall"] >= 0.9
                                                          for k in kinds.values())
                           and sim["targets"][name][cond]["false_alarm_pct"] <= 0.05)
    cut = numbers["airborne"]["cut"]
    assert cut["profile"] == "airborne" and cut["gross_found"] <= cut["gross"]
    assert len(cut["missed_gross_gaps_m"]) == cut["gross"] - cut["gross_found"]
    assert "`patch`: " in text and "target >= 50,000 points/s" in text
    command = text.split("## The temporal command against laspy I/O")[1]
    assert "| A_100.las | " in command and "Largest ratio " in command
    assert len(numbers["command"]["ratios"]) == 1 and numbers["command"]["ratios"][0] > 0
    speed = numbers["speed"]["temporal"]
    assert speed["points"] > 0 and speed["peak_rss_mb"] >= speed["rss_before_mb"] > 0
    assert speed["run_peak_rss_mb"] >= speed["rss_before_mb"]
    # a second run reuses the cached clouds: same files, untouched
    mtimes = {p: p.stat().st_mtime_ns for p in cached}
    assert main(["bench", "--quick", "--scale", "0.03", "--cache", str(tmp_path / "cache"),
                 "--isprs", "none", "--wads", "none", "--airborne", "none",
                 "--no-speed"]) == 0
    assert all(p.stat().st_mtime_ns == m for p, m in mtimes.items())


def test_new_registry_detectors_join_the_benchmark(monkeypatch):
    spec = Detector(name="newdet", parameters=DETECTORS["patch"].parameters,
                    run=DETECTORS["patch"].run, summary="new", flag_bit=1 << 15)
    monkeypatch.setitem(DETECTORS, "newdet", spec)
    pipelines = bench.outlier_pipelines()
    assert list(pipelines)[:4] == list(bench.PAPER_PIPELINES)
    assert pipelines["newdet"] == ["newdet"]
    assert "ground" not in pipelines


@pytest.mark.parametrize("table", [paper.TABLE2, paper.TABLE3, paper.TABLE4, paper.TABLE5])
def test_paper_percentages_follow_from_its_counts(table):
    """A check of the transcription: each printed % equals the counts over Table 1's totals."""
    for cloud, row in table.items():
        total = paper.TABLE1[cloud]
        pct = 100 * row["outliers_identified"] / total["outliers"]
        assert row["pct_outliers_identified"] == pytest.approx(pct, abs=0.006)
        flagged = row["outliers_identified"] + row["non_outliers_identified"]
        assert row["pct_cloud_identified"] == pytest.approx(100 * flagged / total["points"],
                                                            abs=0.006)


def test_gaps_to_unlabelled_against_every_distance():
    rng = np.random.default_rng(5)
    xyz = rng.uniform(0, 10, (300, 3))
    labelled = rng.random(300) < 0.2
    missed = labelled & (rng.random(300) < 0.5)
    slow = sorted(min(np.linalg.norm(xyz[i] - xyz[j]) for j in np.flatnonzero(~labelled))
                  for i in np.flatnonzero(missed))
    np.testing.assert_allclose(bench.gaps_to_unlabelled(xyz, labelled, missed), slow)
    assert bench.gaps_to_unlabelled(xyz, labelled, np.zeros(300, bool)).size == 0


def test_bad_folder_is_one_line_usage_error(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["bench", "--quick", "--isprs", str(tmp_path / "missing")])
    assert exc.value.code == 2
    assert capsys.readouterr().err.count("\n") == 1


def test_leave_one_sample_out_chooses_on_the_other_samples():
    # rows: configurations, columns: samples (total error %)
    errors = np.array([[1.0, 9.0, 1.0],
                       [2.0, 2.0, 2.0],
                       [9.0, 1.0, 1.5]])
    chosen, held = bench.loo_choices(errors)
    # without sample 0 the means are 5, 2, 1.25 -> config 2; without 1: 1, 2, 5.25 -> config 0;
    # without 2: 5, 2, 5 -> config 1
    np.testing.assert_array_equal(chosen, [2, 0, 1])
    np.testing.assert_array_equal(held, [9.0, 9.0, 2.0])


def test_seed_lists():
    assert bench.parse_seeds("0-2, 7,10-11") == (0, 1, 2, 7, 10, 11)
    assert bench.seed_spec([0, 1, 2, 7, 10, 11]) == "0-2, 7, 10, 11"
    for bad in ("x", "3-1", "-2", "1-"):
        with pytest.raises(ValueError, match="seed"):
            bench.parse_seeds(bad)


def test_reporting_seeds_are_never_tuning_seeds():
    cfg = bench.BenchConfig(seeds=5, tune_seeds=tuple(range(100, 103)))
    assert bench.reporting_seeds(cfg) == (103, 104, 105, 106, 107)
    fresh = bench.reporting_seeds(bench.BenchConfig(seeds=4, fresh=True))
    assert len(set(fresh)) == 4 and not set(fresh) & set(bench.TUNE_SEEDS)
    assert bench.reporting_seeds(bench.BenchConfig(report_seeds=(5, 9))) == (5, 9)
    with pytest.raises(Exception, match="tuning seeds"):
        bench.reporting_seeds(bench.BenchConfig(report_seeds=(1, 9)))


def test_the_command_states_where_reporting_seeds_start():
    from lidar_outliers.cli.bench import REPORT_BASE

    assert REPORT_BASE == bench.REPORT_BASE


@pytest.mark.parametrize(("args", "words"), [
    (["--report-seeds", "1,200"], "--report-seeds: 1 also tuning seed"),
    (["--report-seeds", "200", "--fresh"], "exclude each other"),
    (["--tune-seeds", "a-b"], "--tune-seeds: not a seed"),
])
def test_bad_seed_options_are_one_line_usage_errors(args, words, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["bench", "--quick", *args])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and words in err
