"""`lidar-outliers detect` and `lidar-outliers detectors`: outputs, exit codes, one-line errors."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import laspy
import numpy as np
import pytest

from lidar_outliers.cli import main
from lidar_outliers.detectors import DETECTORS
from lidar_outliers.lasio import inspect_las
from tests.lasfiles import scan_line_cloud, write_las

ROOT = Path(__file__).resolve().parents[3]


@pytest.fixture
def cloud_file(tmp_path):
    rng = np.random.default_rng(7)
    xyz, t, spiked = scan_line_cloud(2000, rng, spikes=20, spike_size=0.5)
    cls = np.where(spiked, 7, 1).astype(np.uint8)
    return write_las(tmp_path / "in.las", xyz, gps_time=t, classification=cls)


def _cli(capsys, *args: str) -> tuple[int, str, str]:
    """Run main() in-process; returns (status, stdout, stderr)."""
    try:
        status = main(list(args))
    except SystemExit as exc:
        status = exc.code if isinstance(exc.code, int) else 1
    out = capsys.readouterr()
    return status, out.out, out.err


def _one_error_line(err: str) -> str:
    lines = err.splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("lidar-outliers: error: ")
    return lines[0]


def test_detect_prints_statistics_and_writes_flagged_cloud(capsys, tmp_path, cloud_file):
    out = tmp_path / "out.laz"
    status, stdout, err = _cli(capsys, "detect", str(cloud_file), "-o", str(out),
                               "--detector", "temporal", "--n1", "4", "--n2", "6",
                               "--sigma", "0.003", "--max-gap", "auto",
                               "--detector", "section", "--section-size", "4",
                               "--reference-classes", "7")
    assert status == 0, err
    stats = json.loads(stdout)
    assert [s["detector"] for s in stats["stages"]] == ["temporal", "section"]
    assert stats["stages"][0]["params"]["n1"] == 4 and stats["stages"][0]["params"]["n2"] == 6
    assert stats["stages"][0]["params"]["sigma"] == 0.003
    assert stats["stages"][1]["params"]["section_size"] == 4.0
    assert stats["stages"][0]["confusion"]["outliers"] == 20
    assert inspect_las(out).compressed  # from the .laz suffix
    las = laspy.read(out)
    assert {"outlier_flags", "temporal_score", "section_score"} <= set(
        las.point_format.extra_dimension_names)
    flagged = np.asarray(las.outlier_flags) != 0
    assert flagged.sum() == stats["overall"]["points_flagged"] > 0
    assert np.all(np.asarray(las.classification)[flagged] == 7)


def test_params_file_flags_and_stats_file(capsys, tmp_path, cloud_file):
    params = tmp_path / "p.json"
    params.write_text(json.dumps({"pipeline": [{"detector": "temporal", "sigma": 0.003}],
                                  "noise_class": 18}))
    stats_file = tmp_path / "s" / "stats.json"
    out = tmp_path / "out.las"
    status, stdout, err = _cli(capsys, "detect", str(cloud_file), "-o", str(out), "--params",
                               str(params), "--no-classify", "--stats", str(stats_file), "-q")
    assert status == 0, err
    assert stdout == ""
    stats = json.loads(stats_file.read_text())
    assert stats["classify"] is False and stats["noise_class"] == 18
    assert stats["stages"][0]["params"]["sigma"] == 0.003
    np.testing.assert_array_equal(laspy.read(out).classification,
                                  laspy.read(cloud_file).classification)
    # --detector groups replace the file's pipeline; --noise-class overrides its noise_class.
    status, stdout, err = _cli(capsys, "detect", str(cloud_file), "-o", str(out), "--params",
                               str(params), "--detector", "section", "--noise-class", "9")
    assert status == 0, err
    stats = json.loads(stdout)
    assert [s["detector"] for s in stats["stages"]] == ["section"]
    assert stats["noise_class"] == 9


@pytest.mark.parametrize(
    ("args", "status", "expected"),
    [
        (["--detector", "temporal", "--n1", "0"],
         2, "--n1 of --detector temporal: Input should be greater than or equal to 1"),
        (["--detector", "temporal", "--sigma", "abc"], 2, "--sigma of --detector temporal"),
        (["--detector", "temporal", "--sigma", "-1"], 2,
             "--sigma of --detector temporal: Input should be greater than 0"),
        (["--detector", "temporal", "--k", "40"], 2, "--k is not a parameter of detector temporal"),
        (["--detector", "median"], 2, "unknown detector 'median'"),
        (["--detector"], 2, "--detector needs a name"),
        (["--noise-class", "300"], 2, "--noise-class: Input should be less than or equal to 255"),
        (["--noise-class", "40"], 2, "noise_class 40 does not fit point format 3"),
        (["--detector", "patch", "--k", "5"], 2, "--k of --detector patch"),
        (["--bogus"], 2, "unrecognized arguments: --bogus"),
    ],
)
def test_bad_parameters_exit_2_with_one_line(capsys, tmp_path, cloud_file, args, status, expected):
    out = tmp_path / "out.las"
    code, stdout, err = _cli(capsys, "detect", str(cloud_file), "-o", str(out), *args)
    assert code == status
    assert expected in _one_error_line(err)
    assert not out.exists()


def test_bad_input_files_exit_1_with_one_line(capsys, tmp_path, cloud_file):
    text = tmp_path / "notes.las"
    text.write_text("x,y,z\n1,2,3\n")
    truncated = tmp_path / "cut.las"
    truncated.write_bytes(cloud_file.read_bytes()[:5000])
    no_time = write_las(tmp_path / "pf0.las", np.zeros((10, 3)), point_format=0)
    laz = write_las(tmp_path / "whole.laz", np.random.default_rng(3).normal(size=(3000, 3)),
                    gps_time=np.arange(3000.0))
    cut_laz = tmp_path / "cut.laz"
    cut_laz.write_bytes(laz.read_bytes()[: laz.stat().st_size // 2])
    laz.unlink()
    bad_params = tmp_path / "bad.json"
    bad_params.write_text('{"pipeline": [{"detector": "temporal", "n_1": 3}]}')
    cases = [
        ([str(text)], 1, "notes.las is not a LAS/LAZ file"),
        ([str(truncated)], 1, "cut.las is truncated: header says 2000 points"),
        ([str(tmp_path / "missing.las")], 1, "cannot read missing.las"),
        ([str(cut_laz), "--detector", "temporal"], 1, "cut.laz is truncated: its compressed"),
        ([str(no_time), "--detector", "temporal"], 1, "the temporal detector needs gps_time"),
        ([str(cloud_file), "--params", str(bad_params)], 2, "pipeline[0].n_1: unknown parameter"),
        ([str(cloud_file), "--params", str(tmp_path / "nope.json")], 2, "cannot read --params"),
    ]
    for args, status, expected in cases:
        out = tmp_path / "out.las"
        code, _, err = _cli(capsys, "detect", *args, "-o", str(out))
        assert code == status, (args, err)
        assert expected in _one_error_line(err), err
        assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".")) == []
        assert not out.exists()


def test_missing_output_and_unknown_command(capsys, cloud_file):
    code, _, err = _cli(capsys, "detect", str(cloud_file))
    assert code == 2 and "required: -o/--output" in _one_error_line(err)
    code, _, err = _cli(capsys, "frobnicate")
    assert code == 2 and "invalid choice: 'frobnicate'" in _one_error_line(err)


def test_detectors_listing_text_and_json(capsys):
    code, text, _ = _cli(capsys, "detectors")
    assert code == 0
    for name, spec in DETECTORS.items():
        assert f"\n{name}  (" in "\n" + text
        for field, info in spec.model.model_fields.items():
            if field != "detector":
                assert "--" + field.replace("_", "-") in text
                assert f"default {json.dumps(info.default)}" in text
    assert "range >= 10 and <= 500" in text  # patch k
    code, raw, _ = _cli(capsys, "detectors", "--json")
    data = json.loads(raw)
    assert list(data["detectors"]) == list(DETECTORS)
    k = next(p for p in data["detectors"]["patch"]["parameters"] if p["name"] == "k")
    assert k == {"name": "k", "type": "int", "default": 40, "range": ">= 10 and <= 500",
                 "description": DETECTORS["patch"].model.model_fields["k"].description}
    assert data["detectors"]["temporal"]["outlier_flags_bit"] == 1
    assert data["detectors"]["ground"]["outlier_flags_bit"] is None
    assert {p["name"] for p in data["pipeline"]} == {
        "pipeline", "profile", "classify", "noise_class", "reference_classes"}


def test_installed_entry_point_in_subprocess(tmp_path, cloud_file):
    """The real program: exit status and one-line error through a separate process."""
    script = Path(sys.executable).with_name("lidar-outliers")
    command = [str(script)] if script.exists() else [sys.executable, "-m", "lidar_outliers.cli"]
    out = tmp_path / "out.las"
    ok = subprocess.run([*command, "detect", str(cloud_file), "-o", str(out), "--detector",
                         "temporal"], capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert ok.returncode == 0, ok.stderr
    assert json.loads(ok.stdout)["stages"][0]["detector"] == "temporal"
    assert ok.stderr == ""  # no progress bar when stderr is not a terminal
    bad = subprocess.run([*command, "detect", str(out), "-o", str(out)], capture_output=True,
                         text=True, timeout=300, cwd=ROOT)
    assert bad.returncode == 2
    assert bad.stderr == "lidar-outliers: error: the output file must differ from the input file\n"
