"""`lidar-outliers detect --trajectory`: the default mobile pipeline with free-space evidence."""

from __future__ import annotations

import json
from pathlib import Path

import laspy
import numpy as np
import pytest

from lidar_outliers.cli import main
from tests.lidar_outliers.cli.test_detect import _cli

TRANSIENT_BIT = 128


@pytest.fixture(scope="module")
def simulated(tmp_path_factory) -> Path:
    """Condition A at scale 0.02 (about 18 k points, 180 outliers), written by the CLI."""
    folder = tmp_path_factory.mktemp("sim")
    assert main(["simulate", "--condition", "A", "--seed", "0", "--scale", "0.02",
                 "--out", str(folder)]) == 0
    return folder / "A_0.las"


def _truth(las_path: Path) -> tuple[np.ndarray, np.ndarray, list[str]]:
    truth = np.load(las_path.with_suffix(".truth.npz"))
    return truth["is_outlier"], truth["kind"], [str(k) for k in truth["kind_names"]]


def _run(capsys, tmp_path: Path, las_path: Path, *extra: str) -> tuple[dict, np.ndarray]:
    out = tmp_path / "out.las"
    status, stdout, err = _cli(capsys, "detect", str(las_path), "-o", str(out), "-q", *extra)
    assert status == 0, err
    return json.loads(stdout), np.asarray(laspy.read(out).outlier_flags)


def _lever_arms(las_path: Path) -> str:
    """The system's lever arms from the truth file, as its calibration report gives them."""
    arms = np.load(las_path.with_suffix(".truth.npz"))["lever_arms"]
    return json.dumps([[int(a[0]), *map(float, a[1:])] for a in arms])


def test_trajectory_adds_free_space_evidence_to_transient(capsys, tmp_path, simulated):
    outlier, _, _ = _truth(simulated)
    stats, flags = _run(capsys, tmp_path, simulated)
    assert stats["profile"] == "mobile" and stats["pipeline_source"] == "default"
    assert [s["detector"] for s in stats["stages"]] == ["transient", "height_field"]
    without = (flags & TRANSIENT_BIT) != 0
    assert "trajectory" not in stats

    # the same pipeline, given the system's lever arms beside its trajectory
    traj = simulated.with_suffix(".trajectory.txt")
    stats, flags = _run(capsys, tmp_path, simulated, "--trajectory", str(traj),
                        "--detector", "transient", "--lever-arms", _lever_arms(simulated),
                        "--detector", "height_field")
    info = stats["stages"][0]["info"]
    assert stats["trajectory"]["used_by"] == "transient"
    assert stats["trajectory"]["name"] == traj.name and stats["trajectory"]["samples"] > 100
    with_traj = (flags & TRANSIENT_BIT) != 0
    # Both counts are reported and the flag is their union.
    assert info["points_flagged"] == int(with_traj.sum())
    assert info["points_flagged_by_free_space"] > 0
    assert info["points_flagged_by_clusters"] == int(without.sum())
    assert np.all(with_traj[without])  # the clusters' flags are kept
    # Free space finds outliers the clusters did not (beams of other pulses passed there).
    assert np.count_nonzero(with_traj & ~without & outlier) > 0


def test_lever_arms_option_reaches_the_detector(capsys, tmp_path, simulated):
    traj = simulated.with_suffix(".trajectory.txt")
    stats, _ = _run(capsys, tmp_path, simulated, "--trajectory", str(traj),
                    "--detector", "transient", "--lever-arms", "[[1, -0.6, 0.45, 0]]")
    assert stats["stages"][0]["params"]["lever_arms"] == [[1, -0.6, 0.45, 0.0]]
    # scanner 1 as given, the others placed from their own points
    arms = stats["stages"][0]["info"]["free_space"]["lever_arms"]
    assert arms["1"] == {"source": "given", "arm": [-0.6, 0.45, 0.0]}
    assert {a["source"] for k, a in arms.items() if k != "1"} <= {"estimated", "none"}


@pytest.mark.parametrize(
    ("content", "words"),
    [
        ("# time x y z\n1 2 3\n", "line 2: 3 columns"),
        ("1 2 3 4\n2 a 3 4\n", "line 2: not numbers"),
        ("1 2 3 4\n1 2 3 4\n", "does not increase"),
        ("1 2 3 4\n", "1 samples"),
        ("1 2 3 4\n2 nan 3 4\n", "NaN"),
    ],
)
def test_bad_trajectory_is_one_line(capsys, tmp_path, simulated, content, words):
    bad = tmp_path / "bad.txt"
    bad.write_text(content)
    status, _, err = _cli(capsys, "detect", str(simulated), "-o", str(tmp_path / "o.las"),
                          "-q", "--trajectory", str(bad))
    assert status == 2  # ParameterError: the --trajectory argument is unusable
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "bad.txt" in lines[0] and words in lines[0], err
    assert not (tmp_path / "o.las").exists()


def test_trajectory_of_another_time_is_refused(capsys, tmp_path, simulated):
    traj = np.loadtxt(simulated.with_suffix(".trajectory.txt"))
    shifted = tmp_path / "later.txt"
    np.savetxt(shifted, traj + np.array([1e5, 0, 0, 0]))
    status, _, err = _cli(capsys, "detect", str(simulated), "-o", str(tmp_path / "o.las"),
                          "-q", "--trajectory", str(shifted))
    assert status == 2 and "do not overlap" in err and len(err.strip().splitlines()) == 1


def test_missing_trajectory_file(capsys, tmp_path, simulated):
    status, _, err = _cli(capsys, "detect", str(simulated), "-o", str(tmp_path / "o.las"),
                          "-q", "--trajectory", str(tmp_path / "nope.txt"))
    assert status == 2 and "cannot read trajectory" in err
