"""`lidar-outliers submit` before it reaches a server: the inputs it sends and the mistakes it
refuses in one line. tests/e2e/test_client.py runs it against the real stack."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from lidar_outliers.cli import build_parser, command_modules
from lidar_outliers.cli.submit import job_inputs, split_argv
from tests.lidar_outliers.cli.test_detect import _cli, _one_error_line


def parse(*argv: str) -> argparse.Namespace:
    """The arguments as `main` hands them to the command."""
    rest, extra = split_argv(list(argv))
    args = build_parser(command_modules("submit")).parse_args(["submit", "in.las", *rest])
    args.extra = extra
    return args


def test_detector_groups_make_the_pipeline_document() -> None:
    args = parse("--detector", "temporal", "--sigma", "0.01", "--detector", "patch", "--k", "30",
                 "--no-classify")
    assert job_inputs(args) == {"pipeline": [{"detector": "temporal", "sigma": 0.01},
                                             {"detector": "patch", "k": 30}],
                                "classify": False}
    assert job_inputs(parse()) == {}  # the service picks the file's default pipeline


def test_params_inline_or_from_a_file(tmp_path: Path) -> None:
    document = '{"pipeline": [{"detector": "section"}], "noise_class": 18}'
    assert job_inputs(parse("--params", document)) == {"pipeline": [{"detector": "section"}],
                                                       "noise_class": 18}
    (tmp_path / "p.json").write_text(document)
    assert job_inputs(parse("--params", str(tmp_path / "p.json"), "--noise-class", "9")) == {
        "pipeline": [{"detector": "section"}], "noise_class": 9}


def test_a_single_process_takes_its_own_inputs() -> None:
    args = parse("--process", "temporal", "--params", '{"n1": 7}', "--noise-class", "18")
    assert job_inputs(args) == {"n1": 7, "noise_class": 18}  # the service checks them


@pytest.mark.parametrize(("argv", "expected"), [
    (["--detector", "temporal", "--n1", "0"], "--n1 of --detector temporal: Input should be"),
    (["--params", "{not json"], "--params is not valid JSON"),
    (["--process", "temporal", "--detector", "patch"], "--detector groups make a pipeline"),
    (["--process", "temporal", "--profile", "mobile"], "--profile chooses a default pipeline"),
])
def test_mistakes_are_refused_before_sending(capsys, monkeypatch, tmp_path: Path,
                                             argv: list[str], expected: str) -> None:
    monkeypatch.setenv("LIDAR_OUTLIERS_SERVER", "http://127.0.0.1:9")  # never reached
    monkeypatch.setenv("LIDAR_OUTLIERS_KEY", "k")
    (tmp_path / "in.las").write_bytes(b"LASF")
    status, out, err = _cli(capsys, "submit", str(tmp_path / "in.las"), *argv)
    assert status == 2 and out == ""
    assert expected in _one_error_line(err)


@pytest.mark.parametrize(("env", "argv", "expected"), [
    ({}, [], "--server is required (or set LIDAR_OUTLIERS_SERVER)"),
    ({"LIDAR_OUTLIERS_SERVER": "http://127.0.0.1:9"}, [], "--key is required"),
    ({}, ["--server", "http://127.0.0.1:9", "--key", "k", "missing.las"], "no such file"),
])
def test_server_key_and_file_are_required(capsys, monkeypatch, tmp_path: Path, env, argv,
                                          expected: str) -> None:
    monkeypatch.delenv("LIDAR_OUTLIERS_SERVER", raising=False)
    monkeypatch.delenv("LIDAR_OUTLIERS_KEY", raising=False)
    for name, value in env.items():
        monkeypatch.setenv(name, value)
    monkeypatch.chdir(tmp_path)
    (tmp_path / "in.las").write_bytes(b"LASF")
    status, _, err = _cli(capsys, "submit", *(argv or ["in.las"]))
    assert status == 2
    assert expected in _one_error_line(err)
