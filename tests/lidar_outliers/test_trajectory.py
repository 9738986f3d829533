"""Trajectory files and the transient detector's free-space evidence through the registry."""

from __future__ import annotations

import numpy as np
import pytest

from algorithms.free_space import detect_free_space, scanner_origins
from algorithms.transient import detect_transient
from lidar_outliers.cloud import Cloud
from lidar_outliers.detectors import DETECTORS, get_detector
from lidar_outliers.errors import ParameterError
from lidar_outliers.tools.simulator import simulate
from lidar_outliers.trajectory import parse_trajectory, read_trajectory


def test_simulator_format_reads_like_loadtxt(tmp_path):
    rng = np.random.default_rng(3)
    traj = np.column_stack([np.cumsum(rng.uniform(0.005, 0.02, 50)) + 1000.0,
                            rng.normal(0, 10, (50, 3))])
    path = tmp_path / "t.trajectory.txt"
    np.savetxt(path, traj, fmt="%.4f", header="time x y z")  # as `simulate` writes it
    np.testing.assert_array_equal(read_trajectory(path), np.loadtxt(path))


def test_csv_with_column_names_and_extra_columns():
    text = "time,x,y,z,heading\n\n1.0,10,20,30,0.5\n# pause\n2.5;11;21;31;0.6\n3\t12\t22\t32\t.7\n"
    expected = np.array([[1.0, 10, 20, 30], [2.5, 11, 21, 31], [3, 12, 22, 32]])
    np.testing.assert_array_equal(parse_trajectory(text), expected)


@pytest.mark.parametrize(
    ("text", "words"),
    [
        ("", "0 samples"),
        ("time x y z\n", "0 samples"),
        ("1 2 3 4\n0.5 2 3 4\n", "line 2: time 0.5 does not increase"),
        ("1 2 3 4\n2 2 inf 4\n", "line 2: NaN or infinite"),
        ("1 2 3 4\n2 2 3\n", "line 2: 3 columns"),
        ("1 2 3 4\n2 2 x 4\n", "line 2: not numbers"),
    ],
)
def test_bad_text_is_one_line(text, words):
    with pytest.raises(ParameterError, match=words) as err:
        parse_trajectory(text, "t.txt")
    assert "\n" not in str(err.value) and "t.txt" in str(err.value)


def test_binary_file_is_refused(tmp_path):
    path = tmp_path / "cloud.las"
    path.write_bytes(b"LASF\xff\xfe\x00\x81" * 10)
    with pytest.raises(ParameterError, match="not a text file"):
        read_trajectory(path)


def test_lever_arms_are_estimated_from_the_points_by_default():
    """No lever arm given: each scanner is placed from its own points, within centimetres of
    where the simulated system mounted it."""
    sim = simulate("A", 1, 0.04)
    cloud = Cloud(sim.xyz, np.zeros(3), sim.gps_time, sim.point_source_id,
                  np.zeros(len(sim.xyz), np.uint8), trajectory=sim.trajectory)
    transient = get_detector("transient")
    assert transient.parameters().lever_arms == ()
    arms = transient.run(cloud, transient.parameters()).info["free_space"]["lever_arms"]
    true = {int(a[0]): a[1:] for a in sim.lever_arms()}
    assert set(arms) == {str(k) for k in true}
    for sid, arm in true.items():
        assert arms[str(sid)]["source"] == "estimated"
        np.testing.assert_allclose(arms[str(sid)]["arm"], arm, atol=0.05)


def test_transient_with_trajectory_is_clusters_or_free_space():
    """The registry's transient = detect_transient OR detect_free_space on the same origins
    (the points detect_transient found persistent seen again), computed here directly; and the
    cloud's local frame is honoured (origin shifted)."""
    sim = simulate("A", 1, 0.04)
    shift = np.array([500.0, -200.0, 30.0])  # the local frame: xyz + origin = file coordinates
    traj_local = sim.trajectory - np.r_[0.0, shift]
    n = len(sim.xyz)
    zeros = np.zeros(n, np.uint8)
    cloud = Cloud(sim.xyz - shift, shift, sim.gps_time, sim.point_source_id, zeros,
                  trajectory=traj_local)
    params = DETECTORS["transient"].parameters()
    result = get_detector("transient").run(cloud, params)

    placed = result.info["free_space"]["lever_arms"]
    arms = {int(k): tuple(v["arm"]) for k, v in placed.items() if v["source"] == "estimated"}
    assert len(arms) == len(placed)
    origin = scanner_origins(sim.gps_time, sim.point_source_id, sim.trajectory, arms)
    found = detect_transient(sim.xyz, sim.gps_time, sim.point_source_id)
    clusters = found.flagged
    free = detect_free_space(sim.xyz, origin, seen_again=found.score == 0,
                             gps_time=sim.gps_time).flagged
    np.testing.assert_array_equal(result.flagged, clusters | free)
    assert result.info["points_flagged_by_free_space"] == int(free.sum()) > 0
    assert result.info["points_flagged_by_clusters"] == int(clusters.sum())
    assert np.all(result.score[result.flagged] > result.critical_value)
    assert np.all(result.score[~result.flagged] < result.critical_value)

    # Without a trajectory: the cluster detector alone, and the info says why.
    cloud.trajectory = None
    alone = get_detector("transient").run(cloud, params)
    np.testing.assert_array_equal(alone.flagged, clusters)
    assert alone.info["free_space"] == "no trajectory file given"


def test_points_outside_the_trajectory_time_are_left_out():
    sim = simulate("A", 2, 0.01)
    n = len(sim.xyz)
    zeros = np.zeros(n, np.uint8)
    half = sim.trajectory[sim.trajectory[:, 0] <= np.median(sim.gps_time)]  # ends mid-survey
    cloud = Cloud(sim.xyz, np.zeros(3), sim.gps_time, sim.point_source_id, zeros,
                  trajectory=half)
    transient = get_detector("transient")
    info = transient.run(cloud, transient.parameters()).info["free_space"]
    inside = (sim.gps_time >= half[0, 0]) & (sim.gps_time <= half[-1, 0])
    assert info["points_covered"] == int(inside.sum()) and info["points_uncovered"] > 0
