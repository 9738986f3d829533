"""The mobile-mapping simulator and `lidar-outliers simulate`."""

from __future__ import annotations

import math

import laspy
import numpy as np
import pytest

from lidar_outliers.cli import main
from lidar_outliers.tools import simulator as sim
from lidar_outliers.tools.simulator import KIND_NAMES, SCANNERS, TABLE1, simulate

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


def test_road_quadric_matches_march():
    scene = sim.Scene(crown=0.3, grade=0.05)  # exaggerated so the curvature matters
    o, d = _rays(40, 1, target_box=((-3, 3), (-7, 7), (-1.0, -0.5)))
    t, _ = sim.hit_road(o, d, scene)

    def below(p):
        return p[2] <= scene.grade * p[0] - scene.crown / scene.half_width**2 * p[1] ** 2

    slow = []
    for oi, di in zip(o, d, strict=True):
        ts = _march(oi, di, below)
        y = oi[1] + ts * di[1] if math.isfinite(ts) else 0.0
        slow.append(ts if abs(y) <= scene.half_width else math.inf)
    _compare(t, slow)


def test_box_matches_march():
    lo, hi = np.array([-1.0, 0.5, 0.2]), np.array([1.5, 2.0, 1.4])
    o, d = _rays(40, 2, ((-4, 4), (-3, 5), (0.5, 3.0)), ((-1.5, 2.0), (0.0, 2.5), (0.0, 1.6)))
    t, n = sim.hit_box(o, d, lo, hi)

    def inside(p):
        return bool(np.all((p >= lo) & (p <= hi)))

    slow = [_march(oi, di, inside) for oi, di in zip(o, d, strict=True)]
    _compare(t, slow)
    hit = np.isfinite(t)
    assert np.all(np.sum(n[hit] * d[hit], axis=1) < 0)  # the entry face looks at the scanner


def test_vertical_cylinder_matches_march():
    cx, cy, r, z0, z1 = 0.5, -0.3, 0.4, 0.0, 0.8
    o, d = _rays(40, 3, ((-2, 2), (-2, 2), (1.0, 2.5)), ((-0.2, 1.2), (-1.0, 0.4), (0.0, 1.0)))
    t, _ = sim.hit_vertical_cylinder(o, d, cx, cy, r, z0, z1)

    def inside(p):
        return (p[0] - cx) ** 2 + (p[1] - cy) ** 2 <= r * r and z0 <= p[2] <= z1

    _compare(t, [_march(oi, di, inside) for oi, di in zip(o, d, strict=True)])


def test_tilted_cylinder_matches_march():
    p0 = np.array([0.0, -1.0, 1.0])
    axis = np.array([0.0, np.cos(0.4), np.sin(0.4)])
    o, d = _rays(40, 4, ((-1, 1), (-1, 1), (2.0, 3.0)), ((-0.4, 0.4), (-1.0, 1.5), (0.5, 2.5)))
    radius, length = 0.25, 2.5
    t, _ = sim.hit_cylinder_axis(o, d, p0, np.tile(axis, (len(o), 1)), radius, length)

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
    t_in, t_out = sim.hit_ellipsoid(o, d, c, semi)

    def inside(p):
        return np.sum(((p - c) / semi) ** 2) <= 1.0

    _compare(t_in, [_march(oi, di, inside) for oi, di in zip(o, d, strict=True)])
    assert np.all(t_out[np.isfinite(t_in)] >= t_in[np.isfinite(t_in)])


# ------------------------------------------------------------------ the simulated survey


@pytest.fixture(scope="module")
def cloud_b():
    return simulate("B", seed=7, scale=1.0)


def test_same_seed_same_cloud_other_seed_other_cloud():
    a1 = simulate("A", seed=3, scale=0.08)
    a2 = simulate("A", seed=3, scale=0.08)
    a3 = simulate("A", seed=4, scale=0.08)
    for name in ("xyz", "gps_time", "intensity", "kind", "scan_angle"):
        np.testing.assert_array_equal(getattr(a1, name), getattr(a2, name))
    assert len(a1) != len(a3) or not np.array_equal(a1.xyz, a3.xyz)


@pytest.mark.parametrize("condition, scale, count_tol", [("B", 1.0, 0.1), ("C", 1.0, 0.1),
                                                         ("A", 0.5, 0.15)])
def test_point_counts_and_outlier_shares_follow_table1(condition, scale, count_tol, cloud_b):
    cloud = cloud_b if condition == "B" else simulate(condition, seed=7, scale=scale)
    n_paper, out_paper = TABLE1[condition]
    assert abs(len(cloud) / (n_paper * scale) - 1) < count_tol
    share = cloud.is_outlier.mean()
    assert abs(share / (out_paper / n_paper) - 1) < 0.3
    assert np.array_equal(cloud.is_outlier, cloud.kind != 0)


def test_outlier_character_per_condition(cloud_b):
    a = simulate("A", seed=1, scale=0.5)
    kinds_a = np.bincount(a.kind, minlength=len(KIND_NAMES))
    # A: two big clumps (exhaust, water) dominate, arm streaks are a minority
    assert kinds_a[sim.EXHAUST] > 1000 and kinds_a[sim.WATER] > 1000
    assert 0 < kinds_a[sim.ARM] < kinds_a[sim.EXHAUST]
    # clump outliers float above the road, as extra first returns of two
    clump = np.isin(a.kind, (sim.EXHAUST, sim.WATER))
    road = a.scene_height(a.xyz[clump])
    assert np.all(a.xyz[clump, 2] > road)
    assert np.all(a.return_number[clump] == 1) and np.all(a.number_of_returns[clump] == 2)
    # B: arm streaks and small clumps; C: most within a few cm of the surface
    assert np.bincount(cloud_b.kind, minlength=6)[sim.ARM] > 0
    c = simulate("C", seed=1, scale=1.0)
    near = c.kind == sim.NEAR_SURFACE
    assert near.sum() > c.is_outlier.sum() / 2
    dz = c.xyz[near, 2] - c.scene_height(c.xyz[near])
    assert np.all((dz > 0.0) & (dz < 0.08))
    assert np.bincount(c.kind, minlength=6)[sim.ARM] == 0


def test_time_is_ordered_per_scanner_and_lines_break_at_the_sky(cloud_b):
    period = 1.0 / SCANNERS[0].scan_hz
    pulse = 1.0 / SCANNERS[0].pulse_hz
    for sid in (1, 2):
        t = cloud_b.gps_time[cloud_b.point_source_id == sid]
        steps = np.diff(t)
        assert np.all(steps >= 0)
        # within a revolution the beams that look at the sky return nothing: a gap of at least
        # a third of a revolution in nearly every revolution, while the hits come pulse by pulse
        rev = np.floor((t - t[0]) / period)
        starts = np.flatnonzero(np.diff(rev)) + 1
        biggest = np.maximum.reduceat(np.concatenate([[0.0], steps]), starts)
        assert np.median(biggest) > period / 3
        positive = steps[steps > 0]
        assert np.median(positive) == pytest.approx(pulse, rel=1e-3)


def test_command_writes_readable_las_with_truth(tmp_path):
    status = main(["simulate", "--condition", "A", "--seed", "2", "--out", str(tmp_path),
                   "--scale", "0.08"])
    assert status == 0
    las = laspy.read(tmp_path / "A_2.las")
    truth = np.load(tmp_path / "A_2.truth.npz")
    cloud = simulate("A", seed=2, scale=0.08)
    assert str(las.header.version) == "1.4" and las.header.point_format.id == 6
    np.testing.assert_allclose(las.header.scales, 0.001)
    assert len(las) == len(cloud) == len(truth["is_outlier"])
    np.testing.assert_allclose(np.column_stack([las.x, las.y, las.z]), cloud.xyz, atol=0.0006)
    np.testing.assert_array_equal(las.gps_time, cloud.gps_time)
    assert set(np.unique(las.point_source_id)) == {1, 2}
    assert np.all(np.asarray(las.classification) == 0)
    np.testing.assert_allclose(las.scan_angle * 0.006, cloud.scan_angle, atol=0.0031)
    np.testing.assert_array_equal(truth["is_outlier"], cloud.is_outlier)
    assert list(truth["kind_names"]) == list(KIND_NAMES)
    traj = np.loadtxt(tmp_path / "A_2.trajectory.txt")
    assert traj.shape[1] == 4 and np.all(np.diff(traj[:, 0]) > 0)


def test_bad_scale_is_one_line_usage_error(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["simulate", "--condition", "A", "--out", str(tmp_path), "--scale", "3"])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "--scale" in err
