"""Where each profile scanner sits on the vehicle, from its own points and the trajectory.

Free-space evidence needs every beam's origin: the trajectory's reference point plus the
scanner's lever arm (forward, left, up in the vehicle frame). A lever arm guessed from another
vehicle sends beams through static surfaces. The data carries the arm: a profile scanner's
mirror turns at a constant rate, so the direction of its beam is a linear function of time,
theta(t) = omega t + phi, and every beam of the scanner leaves one point of the vehicle.

In the vehicle frame (the points minus the trajectory's position, turned by its heading, as
:func:`algorithms.free_space.scanner_origins` places scanners) the scanner's points lie in its
scan plane through the arm a. So:

1. the plane: the least-squares plane of the points (refitted without the points farther than
   ``PLANE_TRIM`` robust sigmas from it) gives the arm's offset across the plane;
2. the rate: with in-plane coordinates w_i of the points and a guess c of the arm in the plane
   (the reference point's projection first), the beam angles alpha_i = angle(w_i - c) follow
   omega t_i + phi; omega is the peak of the periodogram |sum exp(i (alpha_i - omega t_i))| over
   mirror rates of ``MIN_RATE_HZ``-``MAX_RATE_HZ`` turns a second, either sense, refined on
   longer spans of time; phi is the argument of that sum;
3. the arm in the plane: each beam's direction u_i = (cos theta_i, sin theta_i) gives one
   linear equation (w_i - c) x u_i = 0 in c (the point lies on its beam); the least-squares c
   is refitted with the new angles until it moves less than a millimetre.

The fit is accepted when the beams' median angular residual is below ``MAX_RESIDUAL_RAD``
(the points of a scanner that does not turn at a constant rate in one plane, such as a
multi-beam spinning head, do not fit and the scanner is reported without an arm). Vehicle roll
and pitch (not in a trajectory of positions) tilt the plane by a few degrees and are absorbed
in phi and the plane's thickness. Pure numpy.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

#: Mirror rates searched, turns per second (profile scanners of mobile systems: 10-500 Hz).
MIN_RATE_HZ = 10.0
MAX_RATE_HZ = 500.0
#: Points of one scanner used for the fit (a spread sample in time order).
SAMPLE_POINTS = 20_000
#: Points farther from the first plane than this many robust sigmas are left out of the refit.
PLANE_TRIM = 3.0
#: Median angle (radians) between the beams fitted and the directions to their points, at most.
MAX_RESIDUAL_RAD = 0.01
#: The arm's standard deviation (metres) in the plane, at most.
MAX_ARM_SIGMA = 0.05
#: Points of the first, coarse periodogram at most (a spread sample: its peak is as sharp).
COARSE_POINTS = 512
#: Rounds of the in-plane fit at most.
MAX_ROUNDS = 20


@dataclass
class ArmFit:
    """One scanner's lever arm (forward, left, up metres; None: not found) and how it fitted."""

    arm: tuple[float, float, float] | None
    info: dict[str, Any] = field(default_factory=dict)


def vehicle_frame(points: np.ndarray, position: np.ndarray, heading: np.ndarray) -> np.ndarray:
    """(n, 3) forward, left, up of each point from the vehicle's reference point at its time."""
    rel = points - position
    c, s = np.cos(heading), np.sin(heading)
    return np.column_stack([c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1],
                            rel[:, 2]])


def scan_plane(q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Normal (3,), a point on it (3,) and an in-plane basis (2, 3) of the points' plane,
    refitted without the points off it by more than ``PLANE_TRIM`` robust sigmas."""
    keep = np.ones(len(q), dtype=bool)
    for _ in range(2):
        centre = q[keep].mean(axis=0)
        _, _, vt = np.linalg.svd(q[keep] - centre, full_matrices=False)
        normal = vt[2]
        off = np.abs((q - centre) @ normal)
        sigma = 1.4826 * np.median(off[keep]) + 1e-9
        keep = off <= PLANE_TRIM * sigma
    return normal, centre, vt[:2]


def _coherence(alpha: np.ndarray, t: np.ndarray, omegas: np.ndarray) -> np.ndarray:
    """|mean exp(i (alpha - omega t))| for each candidate omega."""
    phase = alpha[None, :] - omegas[:, None] * t[None, :]
    return np.abs(np.exp(1j * phase).mean(axis=1))


def mirror_rate(alpha: np.ndarray, t: np.ndarray, guess: float | None = None) -> float:
    """omega (rad/s, signed) of beam angles ``alpha`` at increasing times ``t`` (seconds).

    The periodogram's peak on a short span (half the rate taken when it is as coherent: an arc
    of returns also lines up at twice the rate), refined on spans four times longer, then by
    the least-squares slope of the remaining phase against time. ``guess``: a rate already
    that close (the previous round's), refined by the slope only.
    """
    t = t - t[0]
    if guess is not None:
        return _refine_rate(alpha, t, guess)
    span = min(0.25, float(t[-1]))
    grid = np.arange(2 * np.pi * MIN_RATE_HZ, 2 * np.pi * MAX_RATE_HZ, np.pi / (4 * span))
    omegas = np.concatenate([-grid[::-1], grid])
    use = np.flatnonzero(t <= span)
    use = use[np.linspace(0, use.size - 1, min(use.size, COARSE_POINTS)).astype(np.int64)]
    power = _coherence(alpha[use], t[use], omegas)
    best = float(omegas[np.argmax(power)])
    half = _coherence(alpha[use], t[use], np.array([best / 2]))[0]
    if abs(best / 2) >= 2 * np.pi * MIN_RATE_HZ and half >= 0.8 * power.max():
        best /= 2
    while span < t[-1]:
        span *= 4.0
        use = t <= span
        omegas = best + np.pi / (4 * span) * np.arange(-16, 17)
        best = float(omegas[np.argmax(_coherence(alpha[use], t[use], omegas))])
    return _refine_rate(alpha, t, best)


def _refine_rate(alpha: np.ndarray, t: np.ndarray, best: float) -> float:
    """omega refined by the least-squares slope of the phase left against time."""
    for _ in range(3):
        r = np.angle(np.exp(1j * (alpha - best * t)))
        r = np.angle(np.exp(1j * (r - np.angle(np.exp(1j * r).mean()))))  # centred at 0
        slope = np.polyfit(t, r, 1)[0]
        best += float(slope)
    return best


def _in_plane_arm(w: np.ndarray, t: np.ndarray, c: np.ndarray
                  ) -> tuple[np.ndarray, float, float, float, float]:
    """The arm in the plane (2,), omega, phi, the median angular residual and the arm's
    standard deviation (metres, largest direction), from a guess c.

    The rate is read from the farther half of the points (an error in c turns their angles
    least); c from every point ahead of its beam, each equation divided by the point's range
    (an angular residual: the vehicle's roll moves a far point's beam most)."""
    omega = phi = 0.0
    spread = float("inf")
    for _ in range(MAX_ROUNDS):
        d = w - c
        rng = np.hypot(d[:, 0], d[:, 1])
        alpha = np.arctan2(d[:, 1], d[:, 0])
        far = rng >= np.median(rng)
        omega = mirror_rate(alpha[far], t[far], omega if omega else None)
        phi = float(np.angle(np.exp(1j * (alpha[far] - omega * t[far])).mean()))
        theta = omega * t + phi
        u = np.column_stack([np.cos(theta), np.sin(theta)])
        # (w - c) x u = 0  ->  c_x u_y - c_y u_x = w_x u_y - w_y u_x
        a = np.column_stack([u[:, 1], -u[:, 0]]) / np.maximum(rng, 0.5)[:, None]
        b = (w[:, 0] * u[:, 1] - w[:, 1] * u[:, 0]) / np.maximum(rng, 0.5)
        front = np.einsum("ij,ij->i", d, u) > 0  # a point lies ahead of its beam's origin
        if front.sum() < 3:
            break
        new, spread = _solve_with_spread(a[front], b[front])
        moved = float(np.linalg.norm(new - c))
        c = new
        if moved < 1e-3:
            break
    d = w - c
    alpha = np.arctan2(d[:, 1], d[:, 0])
    resid = np.angle(np.exp(1j * (alpha - (omega * t + phi))))
    return c, omega, phi, float(np.median(np.abs(resid))), spread


def _solve_with_spread(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares x of a x = b and the largest standard deviation of x (metres), from the
    residuals' robust sigma: large when the beams span too narrow an arc to pin their origin."""
    x = np.linalg.lstsq(a, b, rcond=None)[0]
    r = b - a @ x
    sigma = 1.4826 * float(np.median(np.abs(r - np.median(r))))
    try:
        cov = sigma**2 * np.linalg.inv(a.T @ a)
    except np.linalg.LinAlgError:
        return x, float("inf")
    return x, float(np.sqrt(max(np.linalg.eigvalsh(cov).max(), 0.0)))


def fit_lever_arm(points: np.ndarray, gps_time: np.ndarray, position: np.ndarray,
                  heading: np.ndarray, sample: int = SAMPLE_POINTS) -> ArmFit:
    """The lever arm of one profile scanner (module docstring) from its points (n, 3), their
    times (n,) and the vehicle's reference position (n, 3) and heading (n,) at those times;
    at most ``sample`` of the points (spread in time) are fitted."""
    n = len(points)
    if n < 100:
        return ArmFit(None, {"points": n, "reason": "fewer than 100 points"})
    order = np.argsort(gps_time, kind="stable")
    pick = order[np.linspace(0, n - 1, min(n, sample)).astype(np.int64)]
    q = vehicle_frame(points[pick], position[pick], heading[pick])
    t = gps_time[pick] - gps_time[pick][0]
    normal, centre, basis = scan_plane(q)
    w = (q - centre) @ basis.T
    c0 = (np.zeros(3) - centre) @ basis.T  # the reference point, projected into the plane
    c, omega, phi, resid, spread = _in_plane_arm(w, t, c0)
    arm = centre + c @ basis
    info = {"points": n, "mirror_hz": round(abs(omega) / (2 * np.pi), 3),
            "median_angle_residual_rad": round(resid, 5),
            "arm_sigma_m": round(spread, 4),
            "plane_normal": [round(float(v), 4) for v in normal]}
    if not resid <= MAX_RESIDUAL_RAD:
        info["reason"] = (f"the beams do not turn at one rate in one plane (median residual "
                          f"{resid:.3f} rad > {MAX_RESIDUAL_RAD})")
        return ArmFit(None, info)
    if not spread <= MAX_ARM_SIGMA:
        info["reason"] = (f"the beams span too narrow an arc to pin their origin (standard "
                          f"deviation {spread:.3f} m > {MAX_ARM_SIGMA} m)")
        return ArmFit(None, info)
    return ArmFit((float(arm[0]), float(arm[1]), float(arm[2])), info)


def fit_lever_arms(points: np.ndarray, gps_time: np.ndarray, source: np.ndarray,
                   position: np.ndarray, heading: np.ndarray) -> dict[int, ArmFit]:
    """:func:`fit_lever_arm` for each scanner (``source``: point_source_id of each point)."""
    fits = {}
    for sid in np.unique(source):
        m = source == sid
        fits[int(sid)] = fit_lever_arm(points[m], gps_time[m], position[m], heading[m])
    return fits
