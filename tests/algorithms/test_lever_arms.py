"""lever_arms: a profile scanner placed from its own points, against a synthetic vehicle whose
scanner sits at a known arm; a scanner that does not turn at one rate is refused."""

from __future__ import annotations

import numpy as np

from algorithms.free_space import scanner_origins, vehicle_pose
from algorithms.lever_arms import fit_lever_arm, mirror_rate


def drive(rng: np.random.Generator, arm: tuple[float, float, float], rate_hz: float,
          uniform: bool = True):
    """A vehicle on a gentle curve at 8 m/s; one scanner at ``arm`` whose plane leans 30
    degrees from across the drive, its beam turning ``rate_hz`` turns a second (or pointing
    anywhere in the plane: ``uniform`` False). Each pulse returns from 3-40 m away."""
    t_traj = np.arange(0.0, 6.0, 0.01)
    heading = 0.05 * t_traj
    x = np.cumsum(8.0 * np.cos(heading)) * 0.01
    y = np.cumsum(8.0 * np.sin(heading)) * 0.01
    traj = np.column_stack([t_traj, x, y, np.full_like(x, 2.0)])
    t = np.sort(rng.uniform(0.5, 5.5, 20_000))
    theta = 2 * np.pi * rate_hz * t if uniform else rng.uniform(0, 2 * np.pi, t.size)
    yaw = np.radians(30.0)
    u = np.array([np.sin(yaw), -np.cos(yaw), 0.0])  # in-plane horizontal, vehicle frame
    w = np.array([0.0, 0.0, -1.0])  # in-plane down
    d_vehicle = np.outer(np.sin(theta), u) + np.outer(np.cos(theta), w)
    pos, h = vehicle_pose(t, traj)
    c, s = np.cos(h), np.sin(h)
    d = np.column_stack([c * d_vehicle[:, 0] - s * d_vehicle[:, 1],
                         s * d_vehicle[:, 0] + c * d_vehicle[:, 1], d_vehicle[:, 2]])
    origin = scanner_origins(t, np.ones(t.size, int), traj, {1: arm})
    points = origin + d * rng.uniform(3.0, 40.0, t.size)[:, None]
    return points, t, pos, h


def test_an_arm_is_found_to_the_millimetre():
    rng = np.random.default_rng(1)
    arm = (-1.8, 0.6, 0.9)
    points, t, pos, h = drive(rng, arm, rate_hz=97.3)
    fit = fit_lever_arm(points, t, pos, h)
    assert fit.arm is not None
    np.testing.assert_allclose(fit.arm, arm, atol=2e-3)
    assert abs(fit.info["mirror_hz"] - 97.3) < 1e-2


def test_beams_that_do_not_turn_at_one_rate_are_refused():
    rng = np.random.default_rng(2)
    points, t, pos, h = drive(rng, (-1.0, 0.0, 0.5), rate_hz=100.0, uniform=False)
    fit = fit_lever_arm(points, t, pos, h)
    assert fit.arm is None and "one rate" in fit.info["reason"]


def test_mirror_rate_matches_a_brute_force_periodogram():
    rng = np.random.default_rng(3)
    t = np.sort(rng.uniform(0, 2.0, 3000))
    alpha = np.angle(np.exp(1j * (-2 * np.pi * 143.21 * t + 0.7 + rng.normal(0, 0.01, t.size))))
    omegas = 2 * np.pi * np.arange(-300, 300, 0.001)
    power = np.array([abs(np.exp(1j * (alpha - w * t)).mean()) for w in omegas[::50]])
    coarse = omegas[::50][np.argmax(power)]
    assert abs(mirror_rate(alpha, t) - coarse) < 2 * np.pi * 0.05
    assert abs(mirror_rate(alpha, t) / (2 * np.pi) + 143.21) < 1e-3
