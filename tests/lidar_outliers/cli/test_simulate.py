"""`lidar-outliers simulate` and the simulator's analytic ray casting.

The family's draws and the physics of every outlier kind: ``test_simulator.py`` one level up.
"""

from __future__ import annotations

import json
import math

import laspy
import numpy as np
import pytest

from lidar_outliers.cli import main
from lidar_outliers.tools.simulator import KIND_NAMES, simulate
from lidar_outliers.tools.simulator import raycast as rc

# ------------------------------------------------------------------ analytic ray casting
# Each vectorised intersection is compared with a slow per-ray march along the beam that
# brackets the first sign change of the object's implicit function and bisects it.


def _march(o, d, inside, t_max=8.0, step=0.005):
    """First t where inside(point) turns True, by stepping and bisection; inf if never."""
    prev = 1e-6
    if inside(o + prev * d):
        return math.inf
    t = prev
    while t < t_max:
        t += step
        if inside(o + t * d):
            lo, hi = prev, t
            for _ in range(60):
                mid = 0.5 * (lo + hi)
                lo, hi = (lo, mid) if inside(o + mid * d) else (mid, hi)
            return hi
        prev = t
    return math.inf


def _rays(n, seed, origin_box=((-2, 2), (-2, 2), (1.5, 3.0)), target_box=((-2, 2), (-2, 2),
                                                                          (-0.5, 0.5))):
    """n rays from points in origin_box aimed at points in target_box, so many hit."""
    rng = np.random.default_rng(seed)
    o = np.column_stack([rng.uniform(*b, n) for b in origin_box])
    target = np.column_stack([rng.uniform(*b, n) for b in target_box])
    d = target - o
    return o, d / np.linalg.norm(d, axis=1, keepdims=True)


def _compare(fast_t, slow):
    slow = np.array(slow)
    both = np.isfinite(slow) & np.isfinite(fast_t)
    assert np.array_equal(np.isfinite(slow), np.isfinite(fast_t))
    assert both.sum() > 5
    np.testing.assert_allclose(fast_t[both], slow[both], atol=1e-6)


@pytest.mark.parametrize("lift", [0.0, 0.4])
def test_road_quadric_matches_march(lift):
    hw, crown, grade = 6.5, 0.3, 0.05  # exaggerated so the curvature matters
    o, d = _rays(40, 1, target_box=((-3, 3), (-7, 7), (-1.0, -0.5)))
    t, _ = rc.hit_road(o, d, hw, crown, grade, lift=lift)

    def below(p):
        return p[2] <= grade * p[0] - crown / hw**2 * p[1] ** 2 + lift

    slow = []
    for oi, di in zip(o, d, strict=True):
        ts = _march(oi, di, below)
        y = oi[1] + ts * di[1] if math.isfinite(ts) else 0.0
        slow.append(ts if abs(y) <= hw else math.inf)
    _compare(t, slow)


def test_box_matches_march():
    lo, hi = np.array([-1.0, 0.5, 0.2]), np.array([1.5, 2.0, 1.4])
    o, d = _rays(40, 2, ((-4, 4), (-3, 5), (0.5, 3.0)), ((-1.5, 2.0), (0.0, 2.5), (0.0, 1.6)))
    t, n = rc.hit_box(o, d, lo, hi)

    def inside(p):
        return bool(np.all((p >= lo) & (p <= hi)))

    slow = [_march(oi, di, inside) for oi, di in zip(o, d, strict=True)]
    _compare(t, slow)
    hit = np.isfinite(t)
    assert np.all(np.sum(n[hit] * d[hit], axis=1) < 0)  # the entry face looks at the scanner


def test_vertical_cylinder_matches_march():
    cx, cy, r, z0, z1 = 0.5, -0.3, 0.4, 0.0, 0.8
    o, d = _rays(40, 3, ((-2, 2), (-2, 2), (1.0, 2.5)), ((-0.2, 1.2), (-1.0, 0.4), (0.0, 1.0)))
    t, _ = rc.hit_vertical_cylinder(o, d, cx, cy, r, z0, z1)

    def inside(p):
        return (p[0] - cx) ** 2 + (p[1] - cy) ** 2 <= r * r and z0 <= p[2] <= z1

    _compare(t, [_march(oi, di, inside) for oi, di in zip(o, d, strict=True)])


def test_tilted_cylinder_matches_march():
    p0 = np.array([0.0, -1.0, 1.0])
    axis = np.array([0.0, np.cos(0.4), np.sin(0.4)])
    o, d = _rays(40, 4, ((-1, 1), (-1, 1), (2.0, 3.0)), ((-0.4, 0.4), (-1.0, 1.5), (0.5, 2.5)))
    radius, length = 0.25, 2.5
    t, _ = rc.hit_cylinder_axis(o, d, p0, np.tile(axis, (len(o), 1)), radius, length)

    def inside(p):
        s = (p - p0) @ axis
        return 0 <= s <= length and np.linalg.norm(p - p0 - s * axis) <= radius

    # the slow reference has no end caps: compare only rays that enter through the side
    slow = np.array([_march(oi, di, inside) for oi, di in zip(o, d, strict=True)])
    side = np.isfinite(t)
    assert side.sum() > 5
    np.testing.assert_allclose(t[side], slow[side], atol=1e-6)


def test_ellipsoid_matches_march():
    c, semi = np.array([0.2, 0.1, 0.5]), np.array([1.2, 0.7, 0.4])
    o, d = _rays(40, 5, target_box=((-1, 1.4), (-0.6, 0.8), (0.0, 1.0)))
    t_in, t_out = rc.hit_ellipsoid(o, d, c, semi)

    def inside(p):
        return np.sum(((p - c) / semi) ** 2) <= 1.0

    _compare(t_in, [_march(oi, di, inside) for oi, di in zip(o, d, strict=True)])
    assert np.all(t_out[np.isfinite(t_in)] >= t_in[np.isfinite(t_in)])


def test_room_wall_from_inside_matches_march():
    """A beam through a window meets the room's far walls (box_exit), per-ray boxes."""
    lo, hi = np.array([-1.0, 0.0, 0.0]), np.array([2.0, 4.0, 3.0])
    rng = np.random.default_rng(6)
    o = np.column_stack([rng.uniform(-0.9, 1.9, 30), np.full(30, 1e-3), rng.uniform(0.1, 2.9, 30)])
    d = np.column_stack([rng.normal(0, 1, 30), rng.uniform(0.2, 1.0, 30), rng.normal(0, 1, 30)])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t, n = rc.box_exit(o, d, np.tile(lo, (30, 1)), np.tile(hi, (30, 1)))

    def outside(p):
        return not bool(np.all((p >= lo) & (p <= hi)))

    _compare(t, [_march(oi, di, outside) for oi, di in zip(o, d, strict=True)])
    assert np.all(np.sum(n * d, axis=1) < 0)  # the wall faces back into the room


def test_reflection_keeps_the_angle():
    d = np.array([[0.6, 0.0, -0.8], [0.0, -0.6, 0.8]])
    np.testing.assert_allclose(rc.reflect(d, np.array([0.0, 0.0, 1.0])),
                               [[0.6, 0.0, 0.8], [0.0, -0.6, -0.8]])


# ------------------------------------------------------------------ the command


def test_command_writes_readable_las_with_truth(tmp_path):
    status = main(["simulate", "--condition", "A", "--seed", "2", "--out", str(tmp_path),
                   "--scale", "0.03"])
    assert status == 0
    las = laspy.read(tmp_path / "A_2.las")
    truth = np.load(tmp_path / "A_2.truth.npz")
    cloud = simulate("A", seed=2, scale=0.03)
    # a real delivery: LAS 1.4 format 6 at 1 mm, unclassified, one source id per scanner
    assert str(las.header.version) == "1.4" and las.header.point_format.id == 6
    np.testing.assert_allclose(las.header.scales, 0.001)
    assert len(las) == len(cloud) == len(truth["is_outlier"])
    np.testing.assert_allclose(np.column_stack([las.x, las.y, las.z]), cloud.xyz, atol=0.0006)
    np.testing.assert_array_equal(las.gps_time, cloud.gps_time)
    ids = {s.source_id for s in cloud.system.scanners}
    assert set(np.unique(las.point_source_id)) <= ids and len(ids) == len(truth["lever_arms"])
    assert np.all(np.asarray(las.classification) == 0)
    np.testing.assert_allclose(las.scan_angle * 0.006, cloud.scan_angle, atol=0.0031)
    ret, n_ret = np.asarray(las.return_number), np.asarray(las.number_of_returns)
    assert np.all((ret >= 1) & (ret <= n_ret))
    np.testing.assert_array_equal(las.intensity, cloud.intensity)
    # the truth beside it: labels, names, and the system's facts
    np.testing.assert_array_equal(truth["is_outlier"], cloud.is_outlier)
    np.testing.assert_array_equal(truth["kind"], cloud.kind)
    assert list(truth["kind_names"]) == list(KIND_NAMES)
    np.testing.assert_allclose(truth["lever_arms"], np.array(cloud.lever_arms(), dtype=float))
    np.testing.assert_allclose(truth["pose"], cloud.pose())
    assert truth["speed"].shape == (len(cloud.motion.t), 2)
    facts = json.loads(str(truth["facts"]))
    assert facts["system"]["layout"] == cloud.system.layout
    assert len(facts["system"]["scanners"]) == len(ids)
    # the header says nothing of the truth
    assert "lever" not in str(las.header.generating_software)
    traj = np.loadtxt(tmp_path / "A_2.trajectory.txt")
    assert traj.shape[1] == 4 and np.all(np.diff(traj[:, 0]) > 0)
    np.testing.assert_allclose(traj, cloud.trajectory, atol=6e-5)


def test_bad_scale_is_one_line_usage_error(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["simulate", "--condition", "A", "--out", str(tmp_path), "--scale", "3"])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "--scale" in err


def test_negative_seed_is_one_line_usage_error(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["simulate", "--condition", "B", "--out", str(tmp_path), "--seed", "-1"])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "--seed" in err
