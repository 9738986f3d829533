"""free_space: the grid walk against a brute-force beam x point test, origins, and a scene."""

from __future__ import annotations

import numpy as np
import pytest

from algorithms.errors import ParameterError
from algorithms.free_space import (
    detect_free_space,
    grazing_margins,
    ray_point_test,
    scanner_origins,
    see_through_counts,
    surface_at_points,
)


def slow_test(o: np.ndarray, p: np.ndarray, q: np.ndarray, radius: float, margin: float) -> bool:
    """Closest approach of the line o -> p to q, written with an explicit projection matrix."""
    d = (p - o) / np.linalg.norm(p - o)
    s = d @ (q - o)
    perp = (np.eye(3) - np.outer(d, d)) @ (q - o)
    return bool(0 < s < np.linalg.norm(p - o) - margin and perp @ perp < radius**2)


def slow_counts(xyz: np.ndarray, origin: np.ndarray, radius: float, margin: float) -> np.ndarray:
    counts = np.zeros(len(xyz), dtype=int)
    for i in range(len(xyz)):
        for j in range(len(xyz)):
            if i != j and slow_test(origin[i], xyz[i], xyz[j], radius, margin):
                counts[j] += 1
    return counts


def wall_scene(rng: np.random.Generator, n_beams: int = 400):
    """Beams from a scanner moving along x at z = 2 onto a wall at y = 5, plus floating points.

    Returns xyz, origin and the index of the floating points (placed on earlier beams' paths,
    as returns from droplets at another time).
    """
    t = np.sort(rng.uniform(0, 1, n_beams))
    origin = np.column_stack([4 * t, np.zeros(n_beams), np.full(n_beams, 2.0)])
    target = np.column_stack([rng.uniform(0, 4, n_beams), np.full(n_beams, 5.0),
                              rng.uniform(0, 3, n_beams)])
    floating = []
    for i in rng.choice(n_beams, 5, replace=False):
        floating.append(origin[i] + 0.5 * (target[i] - origin[i]))
    n_f = len(floating)
    f_origin = origin[:n_f] + [0.0, 0.0, 0.5]  # seen by other beams, from elsewhere
    xyz = np.vstack([target, floating])
    org = np.vstack([origin, f_origin])
    return xyz, org, np.arange(n_beams, n_beams + n_f)


def test_ray_point_test_matches_projection():
    rng = np.random.default_rng(1)
    for _ in range(2000):
        o, p = rng.normal(size=3), rng.normal(size=3) * 3
        q = o + rng.uniform(-0.2, 1.2) * (p - o) + rng.normal(size=3) * 0.05
        assert ray_point_test(o, p, q, 0.05, 0.1) == slow_test(o, p, q, 0.05, 0.1)


@pytest.mark.parametrize("cell", [0.1, 0.37, 2.0])
def test_grid_walk_equals_brute_force(cell):
    rng = np.random.default_rng(2)
    n = 300
    origin = rng.uniform(-1, 1, (n, 3)) + [0, 0, 3]
    xyz = rng.uniform(-1.5, 1.5, (n, 3))
    # put points on the paths of other beams so that the counts are not all zero
    for i in range(0, n, 3):
        j = (i + 1) % n
        xyz[i] = origin[j] + rng.uniform(0.2, 0.8) * (xyz[j] - origin[j])
    fast = see_through_counts(xyz, origin, radius=0.05, margin=0.1, cell=cell)
    slow = slow_counts(xyz, origin, 0.05, 0.1)
    assert slow.sum() > 50
    np.testing.assert_array_equal(fast, slow)


def test_floating_points_found_and_wall_clean():
    rng = np.random.default_rng(3)
    xyz, origin, floating = wall_scene(rng)
    res = detect_free_space(xyz, origin, radius=0.01)
    assert res.flagged[floating].all()
    assert not res.flagged[: floating[0]].any()


def test_shift_invariance():
    rng = np.random.default_rng(4)
    xyz, origin, _ = wall_scene(rng)
    shift = np.array([5e5, 5e6, 100.0])
    a = detect_free_space(xyz, origin, radius=0.01)
    b = detect_free_space(xyz + shift, origin + shift, radius=0.01)
    np.testing.assert_array_equal(a.score, b.score)


def test_scanner_origins_straight_drive_and_stop():
    # drive +x at 2 m/s for 1 s, stop 1 s, drive on
    t = np.arange(0.0, 3.0, 0.01)
    x = np.where(t < 1, 2 * t, np.where(t < 2, 2.0, 2 + 2 * (t - 2)))
    traj = np.column_stack([t, x, np.full_like(t, 1.0), np.full_like(t, 2.0)])
    arms = {1: (-0.6, 0.45, 0.1), 2: (-0.6, -0.45, 0.0)}
    times = np.array([0.5, 1.5, 2.5, 0.5])
    src = np.array([1, 1, 2, 2])
    o = scanner_origins(times, src, traj, arms)
    expect = np.array([[1.0 - 0.6, 1.45, 2.1], [2.0 - 0.6, 1.45, 2.1],
                       [3.0 - 0.6, 0.55, 2.0], [1.0 - 0.6, 0.55, 2.0]])
    np.testing.assert_allclose(o, expect, atol=1e-9)
    back = traj.copy()
    back[:, 1] = -back[:, 1]  # driving -x: forward is -x and left is -y
    o = scanner_origins(np.array([0.5]), np.array([1]), back, arms)
    np.testing.assert_allclose(o, [[-1.0 + 0.6, 1.0 - 0.45, 2.1]], atol=1e-9)


def test_bad_input_is_refused():
    with pytest.raises(ParameterError, match="shape"):
        detect_free_space(np.zeros((4, 3)), np.zeros((3, 3)))
    with pytest.raises(ParameterError, match="NaN"):
        detect_free_space(np.full((4, 3), np.nan), np.zeros((4, 3)))
    with pytest.raises(ParameterError, match="radius"):
        detect_free_space(np.zeros((4, 3)), np.ones((4, 3)), radius=0.0)
    with pytest.raises(ParameterError, match="trajectory"):
        scanner_origins(np.zeros(2), np.ones(2), np.zeros((1, 4)), {})
    with pytest.raises(ParameterError, match="increase"):
        scanner_origins(np.zeros(2), np.ones(2), np.zeros((3, 4)), {})


def slow_surface(xyz: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Each point's k nearest by a full distance sort, the plane by an SVD of them."""
    normal, rough = np.zeros((len(xyz), 3)), np.zeros(len(xyz))
    for i, p in enumerate(xyz):
        nb = xyz[np.argsort(np.linalg.norm(xyz - p, axis=1), kind="stable")[:k]]
        _, sv, vt = np.linalg.svd(nb - nb.mean(axis=0))
        normal[i], rough[i] = vt[-1], sv[-1] / np.sqrt(k)
    return normal, rough


def test_surface_at_points_matches_an_svd_of_the_nearest_points():
    rng = np.random.default_rng(5)
    xyz = np.column_stack([rng.uniform(0, 2, 300), rng.uniform(0, 2, 300),
                           rng.normal(0, 0.01, 300)])
    normal, rough = surface_at_points(xyz, k=10)
    slow_n, slow_r = slow_surface(xyz, 10)
    np.testing.assert_allclose(np.abs(np.einsum("ij,ij->i", normal, slow_n)), 1.0, atol=1e-6)
    np.testing.assert_allclose(rough, slow_r, atol=1e-9)


def wall_at_grazing_incidence(rng: np.random.Generator, noise: float):
    """A scanner driving along x 1 m beside a wall (the plane y = 1) that it hits 15-30 m
    ahead (1.9-3.8 degrees incidence), range noise ``noise`` m; droplets 0.3 m off the wall on
    earlier beams' paths."""
    n = 6000
    x0 = np.sort(rng.uniform(0, 20, n))
    origin = np.column_stack([x0, np.zeros(n), np.full(n, 2.0)])
    end = np.column_stack([x0 + rng.uniform(15, 30, n), np.ones(n), rng.uniform(1.8, 2.2, n)])
    beam = (end - origin) / np.linalg.norm(end - origin, axis=1)[:, None]
    wall = end + beam * rng.normal(0, noise, n)[:, None]
    pick = rng.choice(np.flatnonzero(x0 < 10), 8, replace=False)
    mist = origin[pick] + 0.7 * (end[pick] - origin[pick])
    xyz = np.vstack([wall, mist])
    org = np.vstack([origin, origin[pick] + [0.0, 0.0, 0.4]])
    return xyz, org, np.arange(n, n + len(pick))


def test_a_fixed_margin_sees_through_a_wall_at_grazing_incidence_and_the_beam_margin_not():
    rng = np.random.default_rng(6)
    xyz, origin, mist = wall_at_grazing_incidence(rng, noise=0.005)
    wall = np.ones(len(xyz), bool)
    wall[mist] = False
    fixed = see_through_counts(xyz, origin, radius=0.006, margin=0.08) > 0
    assert np.count_nonzero(fixed[wall]) > 10  # the wall's own points seen through
    res = detect_free_space(xyz, origin, radius=0.006, margin=0.08)
    assert not res.flagged[wall].any()
    assert res.flagged[mist].all()
    assert res.info["beams_with_grazing_margin"] > len(xyz) // 2


def test_grazing_margin_is_radius_and_roughness_over_the_sine():
    # a flat noiseless grid: roughness 0, so the margin is radius / sin(angle) or the least
    g = np.stack(np.meshgrid(np.arange(0, 3, 0.1), np.arange(0, 3, 0.1)), -1).reshape(-1, 2)
    xyz = np.column_stack([g, np.zeros(len(g))])
    steep = xyz + [0.0, 0.0, 10.0]  # straight down: sin = 1
    flat = xyz + [-100.0, 0.0, np.tan(np.radians(3.0)) * 100.0]  # 3 degrees to the plane
    np.testing.assert_allclose(grazing_margins(xyz, steep, radius=0.006, margin=0.08), 0.08)
    want = 0.006 / np.sin(np.radians(3.0))
    got = grazing_margins(xyz, flat, radius=0.006, margin=0.0)
    np.testing.assert_allclose(got, want, rtol=1e-3)


def test_a_point_seen_again_wins_over_the_beam_through_it():
    """A multipath echo at a false range behind a wall: its beam passes through the wall's
    points. Those were recorded again at another moment (static), so they stay and the beam,
    whose own return nobody saw again, is no evidence; without that knowledge the wall is
    flagged."""
    rng = np.random.default_rng(8)
    xyz, origin, floating = wall_scene(rng)
    wall_point = 10
    echo = origin[0] + 1.5 * (xyz[wall_point] - origin[0])  # straight through it, 1.5x range
    xyz = np.vstack([xyz, echo])
    origin = np.vstack([origin, origin[0]])
    echo_i = len(xyz) - 1
    blind = detect_free_space(xyz, origin, radius=0.01)
    assert blind.flagged[wall_point]
    again = np.ones(len(xyz), bool)
    again[floating] = again[echo_i] = False
    res = detect_free_space(xyz, origin, radius=0.01, seen_again=again)
    assert not res.flagged[wall_point]
    assert not res.flagged[again].any()
    assert res.info["beams_counted"] == int(again.sum())


def test_beam_returns_equal_a_loop_over_the_points():
    from algorithms.free_space import beam_returns

    rng = np.random.default_rng(12)
    origin = np.tile([0.0, 0.0, 2.0], (600, 1))
    direction = rng.normal(size=(60, 3))
    direction /= np.linalg.norm(direction, axis=1)[:, None]
    beam = np.repeat(direction, 10, axis=0)  # ten pulses along each of 60 beams
    xyz = origin + beam * rng.uniform(4.9, 5.1, (600, 1)) + rng.normal(0, 0.004, (600, 3))
    t = np.arange(600) * 1e-3
    t[1] = t[0]  # a second return of the first pulse: not another pulse
    points = np.arange(0, 600, 7)
    got = beam_returns(xyz, origin, t, points, radius=0.006, depth=0.08)
    want = []
    for p in points:
        u = (xyz[p] - origin[p]) / np.linalg.norm(xyz[p] - origin[p])
        count = 0
        for q in range(600):
            d = xyz[q] - xyz[p]
            along = d @ u
            across = np.linalg.norm(d - along * u)
            count += bool(t[q] != t[p] and abs(along) <= 0.08 and across <= 0.006)
        want.append(count)
    np.testing.assert_array_equal(got, want)
    assert got.max() > 0


def test_a_point_its_own_beam_returns_to_is_not_seen_through():
    """A scanner standing still fires the same beam every turn. The edge of a wall 5 m away is
    returned on every other turn and passed on the others (to a wall 9 m away): seen through,
    yet returned to, a surface. A droplet 2 m away, returned once, is passed by every pulse."""
    rng = np.random.default_rng(3)
    scanner = np.array([0.0, 0.0, 1.0])
    turns = 20
    ranges = np.where(np.arange(turns) % 2 == 1, 5.0, 9.0)
    xyz = scanner + np.outer(ranges, [0.0, 1.0, 0.0]) + rng.normal(0, 0.001, (turns, 3))
    xyz = np.vstack([xyz, scanner + [0.0, 2.0, 0.0]])
    times = np.r_[np.arange(turns) * 0.01, 0.5]
    origin = np.tile(scanner, (len(xyz), 1))
    edge = np.flatnonzero(ranges == 5.0)
    blind = detect_free_space(xyz, origin, radius=0.006)
    timed = detect_free_space(xyz, origin, radius=0.006, gps_time=times)
    assert blind.flagged[edge].all() and blind.flagged[-1]
    assert not timed.flagged[edge].any() and timed.flagged[-1]
    assert timed.info["points_returned_to"] == edge.size
    # returned to on fewer than half as many pulses as pass it: still seen through
    assert detect_free_space(xyz, origin, radius=0.006, gps_time=times,
                             hit_ratio=1.0).flagged[edge].all()
