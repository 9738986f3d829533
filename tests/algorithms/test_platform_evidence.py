"""The platform evidence against simple truths: known speeds, beam directions and densities."""

from __future__ import annotations

import numpy as np
import pytest

from algorithms.platform_evidence import (
    occupied_density,
    platform_speed,
    pulse_directions,
    scan_angle_extent,
    usable_time,
)


def sweep(speed: float, seconds: float, lines_per_s: float, half_width: float,
          rate: float = 20_000, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Points of a platform moving along x, its scan sweeping +-half_width across track."""
    rng = np.random.default_rng(seed)
    t = np.sort(rng.uniform(0, seconds, int(rate * seconds))) + 4.0e8
    phase = (t - t[0]) * lines_per_s
    across = half_width * (4 * np.abs(phase - np.floor(phase + 0.5)) - 1)
    return t, np.c_[speed * (t - t[0]) + rng.normal(0, 0.5, t.size), across]


@pytest.mark.parametrize("speed, lines, half_width", [
    (60.0, 70.0, 360.0),   # an aircraft 1000 m up, +-20 degrees
    (10.0, 100.0, 15.0),   # a van's profile scanner across a street
    (0.0, 100.0, 15.0),    # standing still
])
def test_speed_of_a_sweeping_platform(speed, lines, half_width):
    t, xy = sweep(speed, 8.0, lines, half_width)
    est = platform_speed(t, xy)
    assert est.speed == pytest.approx(speed, abs=1.0)
    assert est.windows >= 7 and not est.short
    assert est.low <= est.speed <= est.high


def test_speed_per_source_and_across_time_gaps():
    """Two flight lines, an hour apart and crossing the same ground the other way: the speed of
    each, not the distance between them over the hour."""
    t1, xy1 = sweep(60.0, 4.0, 70.0, 360.0, seed=1)
    t2, xy2 = sweep(60.0, 4.0, 70.0, 360.0, seed=2)
    t = np.r_[t1, t2 + 3600]
    xy = np.r_[xy1, xy2[::-1] * [1, 1]]
    for source in (np.r_[np.zeros(t1.size), np.ones(t2.size)].astype(int), None):
        assert platform_speed(t, xy, source).speed == pytest.approx(60, abs=1.5)


def test_short_slice_gives_short_windows_and_nothing_gives_none():
    t, xy = sweep(10.0, 0.4, 100.0, 15.0)
    est = platform_speed(t, xy)
    assert est.short and est.windows == 1 and est.speed == pytest.approx(10, abs=2)
    assert platform_speed(t[:1000], xy[:1000]).speed is None  # 0.05 s: too short
    assert platform_speed(t[:5], xy[:5]).windows == 0


def test_pulse_directions_down_sideways_and_not_pulses():
    rng = np.random.default_rng(3)
    n = 400
    t = np.repeat(np.arange(n) * 1e-5, 2)
    rn = np.tile([1, 2], n)
    first = rng.uniform(0, 100, (n, 3))
    nadir = np.radians(rng.uniform(0, 20, n))  # an airborne beam, 0-20 degrees off nadir
    beam = np.c_[np.sin(nadir), np.zeros(n), -np.cos(nadir)]
    xyz = np.empty((2 * n, 3))
    xyz[0::2], xyz[1::2] = first, first + 5 * beam
    down = pulse_directions(t, xyz, rn)
    assert down.pulses == n and down.down_share == 1.0
    assert 0 < down.median_nadir_angle < 20
    side = xyz.copy()
    side[1::2] = first + 5 * np.c_[np.cos(nadir), np.zeros(n), np.sin(nadir)]  # upward-ish
    assert pulse_directions(t, side, rn).down_share == 0.0
    # Returns under 1 m apart do not give a direction; repeated return numbers are no pulse.
    close = xyz.copy()
    close[1::2] = first + 0.5 * beam
    assert pulse_directions(t, close, rn).pulses == 0
    assert pulse_directions(t, xyz, np.ones(2 * n, int)).pulses == 0
    # Coarse time stamps (four for the whole file): one "pulse" per stamp, far too many returns.
    coarse = np.floor(np.arange(2 * n) / (n / 2))
    assert pulse_directions(coarse, xyz, rn).pulses == 0


def test_occupied_density_and_scan_angles():
    g = np.arange(0, 20, 0.25) + 0.125  # 16 points per m2 on a 20 m x 20 m square
    xx, yy = np.meshgrid(g, g)
    xy = np.c_[xx.ravel(), yy.ravel()]
    assert occupied_density(xy) == pytest.approx(16)
    far = np.r_[xy, xy + 1000]  # two patches far apart: the bounding box would say 0.0008
    assert occupied_density(far) == pytest.approx(16)
    assert occupied_density(np.zeros((0, 2))) is None
    assert scan_angle_extent(np.full(10, 15.0)) is None
    assert scan_angle_extent(np.array([-20.0, 3.0, 29.0])) == 29.0
    assert scan_angle_extent(None) is None


def test_usable_time():
    assert usable_time(np.array([1.0, 2.0]))
    assert not usable_time(None)
    assert not usable_time(np.zeros(5))
    assert not usable_time(np.array([np.nan, 3.0]))
