"""A mobile-mapping survey of a parking-lot strip, simulated from physics.

The paper's data (an Optech LYNX survey, Leslar, Wang & Hu 2010, section 4, Table 1) is not public.
This module builds the closest honest substitute, in pure numpy:

* a vehicle drives several passes along a strip at walking-to-driving speed and stops for a few
  seconds once (the paper saw false alarms where the vehicle stood still);
* two 2D profile scanners on its roof in a LYNX-like "butterfly" arrangement (scan planes vertical,
  turned +-45 degrees from the driving direction), each sweeping 360 degrees at 150 Hz with a
  100 kHz pulse rate (the LYNX V100 figures);
* every pulse is ray-cast analytically against the scene: asphalt with a crown, a longitudinal
  grade and mm roughness, curbs, a sidewalk, a wall, raised manhole lids, parked cars (boxes),
  poles (cylinders) and, for conditions A and B, a barrier arm moving up and down (a cylinder whose
  axis turns with time). Beams that hit nothing (the sky) give no point, so scan lines break into
  segments; beams within the vehicle's own blind zone are dropped too;
* range noise of a few mm along the beam; intensity from reflectivity, incidence angle and range;
* outliers in the share and character of Table 1: A about 1.0 % in two large clumps above the
  asphalt (exhaust condensation where the vehicle stood, spurious returns over standing water) plus
  streaks on the moving barrier arm; B about 0.3 % in many small clumps plus arm streaks; C about
  0.01 %, most within a few cm of the surface.

Only points over the clipped strip are kept (8 m of asphalt across, 15 m along, everything above
it included), as the paper clipped its three clouds from the survey: cars, curbs, poles and the
wall stand outside it, so they show only as occlusion shadows, while the manhole lids, the arm and
the outliers lie inside. Everything is arrays in, arrays out; writing LAS is the command's job.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import laspy
import numpy as np

from lidar_outliers.atomic import atomic_path
from lidar_outliers.errors import ParameterError
from lidar_outliers.lasio import write_las_data

#: Outlier kinds; code 0 is a real surface point. Index = code.
KIND_NAMES: tuple[str, ...] = (
    "surface",
    "exhaust_plume",
    "water_multipath",
    "barrier_arm",
    "near_surface",
    "isolated",
)
SURFACE, EXHAUST, WATER, ARM, NEAR_SURFACE, ISOLATED = range(len(KIND_NAMES))

# Materials: index into REFLECTIVITY; they only shape the intensity.
ASPHALT, WET, CONCRETE, WALL, CAR, POLE, LID, ARM_PAINT, FOG = range(9)
REFLECTIVITY = np.array([0.12, 0.04, 0.35, 0.45, 0.6, 0.4, 0.22, 0.85, 0.08])

#: Table 1 of the paper: total points and outliers per cloud.
TABLE1 = {"A": (1098689, 11035), "B": (295147, 872), "C": (237740, 31)}


@dataclass(frozen=True)
class Scanner:
    """One 2D profile scanner: mount in the vehicle frame (x forward, y left, z up)."""

    source_id: int
    offset: tuple[float, float, float]
    yaw_deg: float  # direction of the scan-plane normal, from the driving direction
    phase: float  # mirror angle at t = 0, radians
    scan_hz: float = 150.0
    pulse_hz: float = 100_000.0


@dataclass(frozen=True)
class Scene:
    """The strip's geometry in metres; x along the strip, y across, z up (road crown at y = 0)."""

    length: float = 15.0
    half_width: float = 6.5  # curb to curb / 2
    # the clipped cloud: the asphalt the vehicle drove over (the paper's test strips were
    # asphalt); parked cars, curbs, poles and the wall stand outside it but occlude it
    crop_y: tuple[float, float] = (-4.0, 4.0)
    crown: float = 0.06  # road centre above its edges
    grade: float = 0.005  # dz/dx
    curb: float = 0.15
    wall_y: float = 7.4
    wall_height: float = 3.0
    roughness: float = 0.0015  # RMS of the asphalt texture
    range_sigma: float = 0.003
    min_range: float = 2.6  # blind zone around the vehicle
    max_range: float = 80.0

    def road_z(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Height of the asphalt (without texture): z = g x - a y^2."""
        return self.grade * x - self.crown / self.half_width**2 * y**2

    def sidewalk_z(self, x: np.ndarray) -> np.ndarray:
        return self.grade * x - self.crown + self.curb


@dataclass(frozen=True)
class Condition:
    """How one of the paper's three days is reproduced."""

    name: str
    lanes: tuple[float, ...]  # y of each pass; passes alternate direction
    speeds: tuple[float, ...]  # m/s per pass
    stop_seconds: float
    stop_at: float  # fraction of the strip where pass 1 stops (>1: beyond its end)
    outlier_share: float
    arm: bool
    arm_share: float  # part of the outliers that are barrier-arm streaks
    kind_weights: dict[int, float] = field(default_factory=dict)


CONDITIONS: dict[str, Condition] = {
    "A": Condition(
        "A", lanes=(-1.5, 1.5), speeds=(1.37, 1.37), stop_seconds=3.0, stop_at=0.55,
        outlier_share=TABLE1["A"][1] / TABLE1["A"][0], arm=True, arm_share=0.1,
        kind_weights={EXHAUST: 0.55, WATER: 0.45},
    ),
    "B": Condition(
        "B", lanes=(-1.5, 1.5), speeds=(4.55, 4.55), stop_seconds=3.0, stop_at=1.25,
        outlier_share=TABLE1["B"][1] / TABLE1["B"][0], arm=True, arm_share=0.35,
        kind_weights={EXHAUST: 0.5, WATER: 0.5},
    ),
    "C": Condition(
        "C", lanes=(-1.5, 1.5), speeds=(5.7, 5.7), stop_seconds=3.0, stop_at=1.25,
        outlier_share=TABLE1["C"][1] / TABLE1["C"][0], arm=False, arm_share=0.0,
        kind_weights={NEAR_SURFACE: 0.8, ISOLATED: 0.2},
    ),
}

SCANNERS = (
    Scanner(1, offset=(-0.6, 0.45, 2.35), yaw_deg=45.0, phase=0.0),
    Scanner(2, offset=(-0.6, -0.45, 2.35), yaw_deg=-45.0, phase=1.3),
)


@dataclass
class SimulatedCloud:
    """A simulated survey: n points sorted by gps_time, plus the truth and the trajectory.

    xyz (n, 3) float64 metres; gps_time (n,) float64 s; point_source_id (n,) uint16 scanner 1/2;
    intensity (n,) uint16; return_number, number_of_returns (n,) uint8; scan_angle (n,) float32
    degrees from nadir in the scan plane; is_outlier (n,) bool; kind (n,) uint8 codes of
    ``KIND_NAMES``; trajectory (m, 4) time, x, y, z of the vehicle's roof reference point.
    """

    xyz: np.ndarray
    gps_time: np.ndarray
    point_source_id: np.ndarray
    intensity: np.ndarray
    return_number: np.ndarray
    number_of_returns: np.ndarray
    scan_angle: np.ndarray
    is_outlier: np.ndarray
    kind: np.ndarray
    trajectory: np.ndarray
    condition: str
    seed: int
    scale: float

    def __len__(self) -> int:
        return len(self.gps_time)

    def scene_height(self, xyz: np.ndarray) -> np.ndarray:
        """Height (m) of the bare asphalt or sidewalk, without texture, under each (n, 3) point."""
        scene = Scene(length=Scene().length * self.scale)
        x, y = xyz[:, 0], xyz[:, 1]
        return np.where(np.abs(y) <= scene.half_width, scene.road_z(x, y), scene.sidewalk_z(x))


# --------------------------------------------------------------------------------------------
# Trajectory


@dataclass(frozen=True)
class _Pass:
    t0: float
    knots_t: np.ndarray  # piecewise-linear position along x
    knots_x: np.ndarray
    y: float
    heading: float  # +1 along +x, -1 along -x

    @property
    def t1(self) -> float:
        return float(self.knots_t[-1])


def plan_passes(cond: Condition, scene: Scene, scale: float) -> list[_Pass]:
    """Passes along the strip, alternating direction, each starting and ending 8 m outside it.

    Pass 1 stops for ``stop_seconds * scale`` at ``stop_at`` of the strip. Between passes the
    vehicle turns outside the strip (not scanned: 20 s gap in time).
    """
    margin = 8.0
    passes: list[_Pass] = []
    t = 1000.0
    for i, (lane, speed) in enumerate(zip(cond.lanes, cond.speeds, strict=True)):
        heading = 1.0 if i % 2 == 0 else -1.0
        x_a, x_b = -margin, scene.length + margin
        if heading < 0:
            x_a, x_b = x_b, x_a
        if i == 0 and cond.stop_seconds > 0:
            x_stop = cond.stop_at * scene.length
            t_stop = abs(x_stop - x_a) / speed
            t_end = t_stop + cond.stop_seconds * scale + abs(x_b - x_stop) / speed
            kt = np.array([0.0, t_stop, t_stop + cond.stop_seconds * scale, t_end])
            kx = np.array([x_a, x_stop, x_stop, x_b])
        else:
            kt = np.array([0.0, abs(x_b - x_a) / speed])
            kx = np.array([x_a, x_b])
        passes.append(_Pass(t, t + kt, kx, lane, heading))
        t = passes[-1].t1 + 20.0
    return passes


def scanner_rays(p: _Pass, sc: Scanner, t: np.ndarray, scene: Scene):
    """Origin (n, 3), unit direction (n, 3) and mirror angle from nadir (n,) at pulse times t."""
    x = np.interp(t, p.knots_t, p.knots_x)
    h = p.heading
    ox, oy, oz = sc.offset
    # vehicle frame -> world: heading +x (h = 1) or -x (h = -1, a 180 degree turn)
    origin = np.empty((len(t), 3))
    origin[:, 0] = x + h * ox
    origin[:, 1] = p.y + h * oy
    origin[:, 2] = scene.road_z(x, np.full_like(x, p.y)) + oz
    yaw = np.deg2rad(sc.yaw_deg)
    normal = np.array([h * np.cos(yaw), h * np.sin(yaw), 0.0])
    u = np.cross(normal, [0.0, 0.0, 1.0])  # horizontal direction in the scan plane
    phi = np.mod(sc.phase + 2 * np.pi * sc.scan_hz * t, 2 * np.pi)
    d = np.outer(np.sin(phi), u)
    d[:, 2] = -np.cos(phi)
    angle = np.rad2deg(np.where(phi > np.pi, phi - 2 * np.pi, phi))
    return origin, d, angle


# --------------------------------------------------------------------------------------------
# Analytic ray casting: each function returns the ray parameter t (inf = no hit) and the normal.


def _nearest_positive_root(a, b, c):
    """Smaller positive root of a t^2 + b t + c = 0 elementwise (inf if none)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        disc = b * b - 4 * a * c
        sq = np.sqrt(np.where(disc >= 0, disc, np.nan))
        linear = np.abs(a) < 1e-12
        r1 = np.where(linear, -c / b, (-b - sq) / (2 * a))
        r2 = np.where(linear, np.inf, (-b + sq) / (2 * a))
    lo, hi = np.minimum(r1, r2), np.maximum(r1, r2)
    t = np.where(lo > 1e-6, lo, np.where(hi > 1e-6, hi, np.inf))
    return np.where(np.isnan(t), np.inf, t)


def hit_road(o, d, scene: Scene):
    """Ray vs z = g x - a y^2 for |y| <= half_width (a quadric: a quadratic in t)."""
    a_ = scene.crown / scene.half_width**2
    g = scene.grade
    qa = a_ * d[:, 1] ** 2
    qb = 2 * a_ * o[:, 1] * d[:, 1] + d[:, 2] - g * d[:, 0]
    qc = a_ * o[:, 1] ** 2 + o[:, 2] - g * o[:, 0]
    t = _nearest_positive_root(qa, qb, qc)
    y = o[:, 1] + t * d[:, 1]
    t = np.where(np.abs(y) <= scene.half_width, t, np.inf)
    n = np.stack([np.full_like(y, -g), 2 * a_ * np.where(np.isfinite(y), y, 0.0),
                  np.ones_like(y)], axis=1)
    return t, n / np.linalg.norm(n, axis=1, keepdims=True)


def _plane_t(o, d, axis, value):
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (value - o[:, axis]) / d[:, axis]
    return np.where(t > 1e-6, t, np.inf)


def hit_sidewalk(o, d, scene: Scene):
    """Ray vs the plane z = g x - crown + curb, outside the curbs."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (scene.sidewalk_z(o[:, 0]) - o[:, 2]) / (d[:, 2] - scene.grade * d[:, 0])
    t = np.where(t > 1e-6, t, np.inf)
    y = o[:, 1] + t * d[:, 1]
    t = np.where(np.abs(y) > scene.half_width, t, np.inf)
    n = np.tile([-scene.grade, 0.0, 1.0], (len(t), 1))
    return t, n


def hit_curbs(o, d, scene: Scene):
    """Ray vs the two vertical curb faces y = +-half_width, between road edge and sidewalk."""
    best = np.full(len(o), np.inf)
    normal = np.zeros((len(o), 3))
    for side in (-1.0, 1.0):
        t = _plane_t(o, d, 1, side * scene.half_width)
        x = o[:, 0] + t * d[:, 0]
        z = o[:, 2] + t * d[:, 2]
        lo = scene.sidewalk_z(x) - scene.curb
        ok = (z >= lo) & (z <= lo + scene.curb)
        t = np.where(ok, t, np.inf)
        take = t < best
        best = np.where(take, t, best)
        normal[take] = [0.0, -side, 0.0]
    return best, normal


def hit_wall(o, d, scene: Scene):
    t = _plane_t(o, d, 1, scene.wall_y)
    x = o[:, 0] + t * d[:, 0]
    z = o[:, 2] + t * d[:, 2]
    base = scene.sidewalk_z(x)
    t = np.where((z >= base) & (z <= base + scene.wall_height), t, np.inf)
    return t, np.tile([0.0, -1.0, 0.0], (len(t), 1))


def hit_box(o, d, lo, hi):
    """Slab method for an axis-aligned box [lo, hi]; returns entry t and the entry face normal."""
    n = len(o)
    t_in = np.full(n, -np.inf)
    t_out = np.full(n, np.inf)
    face = np.zeros(n, dtype=np.int8)
    with np.errstate(divide="ignore", invalid="ignore"):
        for ax in range(3):
            inv = 1.0 / d[:, ax]
            t1 = (lo[ax] - o[:, ax]) * inv
            t2 = (hi[ax] - o[:, ax]) * inv
            near = np.fmin(t1, t2)
            near = np.where(np.isnan(near), -np.inf, near)
            far = np.where(np.isnan(t1), np.inf, np.fmax(t1, t2))
            later = near > t_in
            face[later] = ax
            t_in = np.where(later, near, t_in)
            t_out = np.minimum(t_out, far)
    t = np.where((t_in <= t_out) & (t_in > 1e-6), t_in, np.inf)
    nrm = np.zeros_like(o)
    rows = np.arange(n)
    nrm[rows, face] = -np.sign(d[rows, face])
    return t, nrm


def hit_vertical_cylinder(o, d, cx, cy, radius, z0, z1, cap=True):
    """Ray vs the side (and top cap) of the cylinder (x-cx)^2+(y-cy)^2 <= r^2, z0 <= z <= z1."""
    wx, wy = o[:, 0] - cx, o[:, 1] - cy
    qa = d[:, 0] ** 2 + d[:, 1] ** 2
    qb = 2 * (wx * d[:, 0] + wy * d[:, 1])
    qc = wx**2 + wy**2 - radius**2
    t_side = _nearest_positive_root(qa, qb, qc)
    z = o[:, 2] + t_side * d[:, 2]
    t_side = np.where((z >= z0) & (z <= z1), t_side, np.inf)
    n = np.zeros_like(o)
    ts = np.where(np.isfinite(t_side), t_side, 0.0)
    n[:, 0] = wx + ts * d[:, 0]
    n[:, 1] = wy + ts * d[:, 1]
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    if cap:
        t_top = _plane_t(o, d, 2, z1)
        r2 = (wx + t_top * d[:, 0]) ** 2 + (wy + t_top * d[:, 1]) ** 2
        t_top = np.where(r2 <= radius**2, t_top, np.inf)
        top = t_top < t_side
        n[top] = [0.0, 0.0, 1.0]
        t_side = np.where(top, t_top, t_side)
    return t_side, n


def hit_cylinder_axis(o, d, p0, axis, radius, length):
    """Ray vs a finite cylinder from p0 along unit axis (per ray, (n, 3)) of the given length."""
    w = o - p0
    dd = d - np.sum(d * axis, axis=1, keepdims=True) * axis
    ww = w - np.sum(w * axis, axis=1, keepdims=True) * axis
    qa = _dot(dd, dd)
    qb = 2 * _dot(dd, ww)
    qc = _dot(ww, ww) - radius**2
    t = _nearest_positive_root(qa, qb, qc)
    tt = np.where(np.isfinite(t), t, 0.0)[:, None]
    s = _dot((w + tt * d), axis)
    t = np.where((s >= 0) & (s <= length), t, np.inf)
    n = ww + tt * dd
    with np.errstate(invalid="ignore"):
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    return t, n


def _dot(a, b):
    return np.einsum("ij,ij->i", a, b)


def hit_ellipsoid(o, d, centre, semi):
    """Entry and exit t of a ray through an axis-aligned ellipsoid (inf, inf when it misses)."""
    oo = (o - centre) / semi
    dd = d / semi
    qa = _dot(dd, dd)
    qb = 2 * _dot(oo, dd)
    qc = _dot(oo, oo) - 1.0
    disc = qb * qb - 4 * qa * qc
    with np.errstate(invalid="ignore"):
        sq = np.sqrt(np.where(disc > 0, disc, np.nan))
    t_in = (-qb - sq) / (2 * qa)
    t_out = (-qb + sq) / (2 * qa)
    ok = np.isfinite(t_in) & (t_in > 1e-6)
    return np.where(ok, t_in, np.inf), np.where(ok, t_out, np.inf)


# --------------------------------------------------------------------------------------------
# The scene's objects


@dataclass(frozen=True)
class Objects:
    manholes: np.ndarray  # (m, 3): cx, cy, lid height above the road
    cars: np.ndarray  # (c, 6): lo xyz, hi xyz
    poles: np.ndarray  # (p, 2): cx, cy
    puddles: np.ndarray  # (q, 4): cx, cy, semi-axis x, semi-axis y (wet asphalt)
    texture: np.ndarray  # (k, 4): kx, ky, phase, amplitude of the asphalt texture
    arm_pivot: np.ndarray  # (3,)
    arm_length: float = 4.0
    arm_radius: float = 0.05
    arm_period: float = 9.0


def build_objects(scene: Scene, rng: np.random.Generator) -> Objects:
    """Place the strip's objects; positions scale with the strip length, sizes do not."""
    L = scene.length
    n_man = max(1, round(3 * L / 20))
    manholes = np.column_stack([
        rng.uniform(0.1, 0.9, n_man) * L,
        rng.uniform(-3.5, 3.5, n_man),
        rng.uniform(0.01, 0.03, n_man),
    ])
    cars = []
    for x0 in np.arange(1.0, L - 4.0, 5.5):
        if rng.random() < 0.75:  # some bays are empty
            y_side = 1.0 if rng.random() < 0.6 else -1.0
            y0 = y_side * 5.0 - 0.9  # parking bays just outside the clipped strip
            z0 = scene.road_z(np.array([x0]), np.array([y_side * 5.0]))[0]
            cars.append([x0, y0, z0 + 0.25, x0 + 4.5, y0 + 1.8, z0 + 1.5])
    cars_arr = np.array(cars, dtype=float).reshape(-1, 6)
    poles = np.column_stack([np.arange(3.0, L, 9.0), np.full(len(np.arange(3.0, L, 9.0)), -7.0)])
    n_pud = max(1, round(2 * L / 20))
    # the first puddle is the large one of cloud A, away from where the vehicle stops
    big = [rng.uniform(0.8, 0.9) * L, rng.uniform(2.0, 3.0), min(1.6, 0.3 * L), 1.0]
    puddles = np.vstack([big, np.column_stack([
        rng.uniform(0.15, 0.85, n_pud) * L,
        rng.uniform(-3.0, 3.0, n_pud),
        rng.uniform(0.8, 1.6, n_pud),
        rng.uniform(0.5, 1.0, n_pud),
    ])])
    # asphalt texture: a few sinusoids of 3-40 cm wavelength summing to the roughness RMS
    k = 12
    wl = rng.uniform(0.03, 0.4, k)
    ang = rng.uniform(0, np.pi, k)
    texture = np.column_stack([
        2 * np.pi / wl * np.cos(ang),
        2 * np.pi / wl * np.sin(ang),
        rng.uniform(0, 2 * np.pi, k),
        np.full(k, scene.roughness * np.sqrt(2.0 / k)),
    ])
    # on the sidewalk; down, the arm reaches y = -2.7, clear of the vehicle in lane -1.5
    pivot = np.array([min(2.0, 0.3 * L), -(scene.half_width + 0.2), 0.0])
    pivot[2] = scene.sidewalk_z(pivot[:1])[0] + 1.0
    return Objects(manholes, cars_arr, poles, puddles, texture, pivot)


def arm_axis(t: np.ndarray, obj: Objects) -> np.ndarray:
    """Unit axis of the barrier arm: across the strip (+y) when down, vertical when up."""
    theta = 0.5 * (np.pi / 2) * (1 - np.cos(2 * np.pi * t / obj.arm_period))
    return np.column_stack([np.zeros_like(t), np.cos(theta), np.sin(theta)])


def cast(o, d, t_pulse, scene: Scene, obj: Objects, arm: bool):
    """First hit of each ray on the static scene, and on the barrier arm in front of it.

    Returns t (n,), material (n,), normal (n, 3) for the static scene (t = inf where the beam
    hits nothing within range), and t_arm (n,), normal_arm (n, 3) where the arm is hit before the
    static scene (t_arm = inf elsewhere). The caller decides when the arm is in operation.
    """
    n = len(o)
    best = np.full(n, np.inf)
    material = np.zeros(n, dtype=np.int8)
    normal = np.zeros((n, 3))

    def take(t, nrm, mat):
        nonlocal best
        m = t < best
        best = np.where(m, t, best)
        material[m] = mat
        normal[m] = nrm[m] if nrm.ndim == 2 else nrm

    take(*hit_road(o, d, scene), ASPHALT)
    take(*hit_sidewalk(o, d, scene), CONCRETE)
    take(*hit_curbs(o, d, scene), CONCRETE)
    take(*hit_wall(o, d, scene), WALL)
    for cx, cy, h in obj.manholes:
        ztop = scene.road_z(np.array([cx]), np.array([cy]))[0] + h
        take(*hit_vertical_cylinder(o, d, cx, cy, 0.3, ztop - 0.1, ztop), LID)
    for box in obj.cars:
        take(*hit_box(o, d, box[:3], box[3:]), CAR)
    for cx, cy in obj.poles:
        z0 = scene.sidewalk_z(np.array([cx]))[0]
        take(*hit_vertical_cylinder(o, d, cx, cy, 0.1, z0, z0 + 4.0, cap=False), POLE)
    in_range = (best >= scene.min_range) & (best <= scene.max_range)
    t_arm = np.full(n, np.inf)
    n_arm = np.zeros((n, 3))
    if arm:
        t_arm, n_arm = hit_cylinder_axis(
            o, d, obj.arm_pivot, arm_axis(t_pulse, obj), obj.arm_radius, obj.arm_length
        )
        ok = (t_arm < best) & (t_arm >= scene.min_range) & (t_arm <= scene.max_range)
        t_arm = np.where(ok, t_arm, np.inf)
    return np.where(in_range, best, np.inf), material, normal, t_arm, n_arm


def texture_height(x, y, obj: Objects) -> np.ndarray:
    """mm-scale asphalt roughness at (x, y): a sum of sinusoids."""
    kx, ky, ph, amp = obj.texture.T
    return np.sin(np.outer(x, kx) + np.outer(y, ky) + ph) @ amp


def in_puddle(x, y, obj: Objects) -> np.ndarray:
    cx, cy, ax, ay = obj.puddles.T
    r = ((x[:, None] - cx) / ax) ** 2 + ((y[:, None] - cy) / ay) ** 2
    return (r <= 1.0).any(axis=1)


# --------------------------------------------------------------------------------------------
# Survey


def _survey(cond: Condition, scene: Scene, obj: Objects, rng, chunk: int = 400_000):
    """Fire every pulse of every pass and keep the first hits that fall inside the strip."""
    names = ("o", "d", "r", "t", "src", "ang", "mat", "cos", "r_arm", "cos_arm")
    cols: dict[str, list[np.ndarray]] = {k: [] for k in names}
    passes = plan_passes(cond, scene, _scale_of(scene))
    box_lo = np.array([0.0, scene.crop_y[0], -0.5])
    box_hi = np.array([scene.length, scene.crop_y[1], 4.6])
    for p in passes:
        for sc in SCANNERS:
            n_pulses = int((p.t1 - p.t0) * sc.pulse_hz)
            for start in range(0, n_pulses, chunk):
                idx = np.arange(start, min(start + chunk, n_pulses))
                tp = p.t0 + idx / sc.pulse_hz
                o, d, ang = scanner_rays(p, sc, tp, scene)
                # cheap cull: beams that never enter the strip's box cannot give a kept point
                t_box, _ = hit_box(o, d, box_lo, box_hi)
                near = np.isfinite(t_box) | _inside(o, box_lo, box_hi)
                o, d, ang, tp = o[near], d[near], ang[near], tp[near]
                r, mat, nrm, r_arm, n_arm = cast(o, d, tp, scene, obj, cond.arm)
                r = np.where(_in_strip(o, d, r, scene), r, np.inf)
                r_arm = np.where(_in_strip(o, d, r_arm, scene), r_arm, np.inf)
                keep = np.flatnonzero(np.isfinite(r) | np.isfinite(r_arm))
                for key, val in (("o", o), ("d", d), ("r", r), ("t", tp), ("ang", ang),
                                 ("mat", mat), ("r_arm", r_arm)):
                    cols[key].append(val[keep])
                cols["src"].append(np.full(len(keep), sc.source_id, dtype=np.uint16))
                cols["cos"].append(np.abs(_dot(nrm[keep], d[keep])))
                cols["cos_arm"].append(np.abs(_dot(n_arm[keep], d[keep])))
    out = {k: np.concatenate(v) for k, v in cols.items()}
    traj = _trajectory_samples(passes, scene)
    return out, traj


def _in_strip(o, d, r, scene: Scene) -> np.ndarray:
    """Whether the point at range r (finite) lies inside the clipped strip (in x and y)."""
    with np.errstate(invalid="ignore"):
        x = o[:, 0] + r * d[:, 0]
        y = o[:, 1] + r * d[:, 1]
        return (np.isfinite(r) & (x >= 0) & (x <= scene.length)
                & (y >= scene.crop_y[0]) & (y <= scene.crop_y[1]))


def _operate_arm(cond: Condition, s: dict) -> dict:
    """Decide when the barrier arm was in operation, and use its hits during that time.

    The arm rests upright outside the strip; it was in operation from the start of the survey
    until it had been hit ``arm_share`` x the condition's outliers times (so its streaks take a
    fixed part of the outlier share at every scale). Pulses that hit the arm then return from it;
    all others return from the static scene (dropping those that saw only sky).
    """
    hits = np.flatnonzero(np.isfinite(s["r_arm"]))
    want = round(cond.arm_share * cond.outlier_share * np.isfinite(s["r"]).sum())
    use = np.zeros(len(s["r"]), dtype=bool)
    if want > 0 and len(hits):
        order = hits[np.argsort(s["t"][hits], kind="stable")]
        use[order[:want]] = True
    s["r"] = np.where(use, s["r_arm"], s["r"])
    s["mat"] = np.where(use, ARM_PAINT, s["mat"]).astype(np.int8)
    s["cos"] = np.where(use, s["cos_arm"], s["cos"])
    s["arm"] = use
    keep = np.isfinite(s["r"])
    return {k: v[keep] for k, v in s.items() if k not in ("r_arm", "cos_arm")}


def _inside(o, lo, hi) -> np.ndarray:
    return np.all((o >= lo) & (o <= hi), axis=1)


def _scale_of(scene: Scene) -> float:
    return scene.length / Scene().length


def _trajectory_samples(passes: list[_Pass], scene: Scene, rate: float = 100.0) -> np.ndarray:
    """Roof reference point at ``rate`` Hz during the scanned passes: (m, 4) time, x, y, z."""
    rows = []
    for p in passes:
        t = np.arange(p.t0, p.t1, 1.0 / rate)
        x = np.interp(t, p.knots_t, p.knots_x)
        y = np.full_like(t, p.y)
        rows.append(np.column_stack([t, x, y, scene.road_z(x, y) + 2.35]))
    return np.concatenate(rows)


def _outlier_clumps(cond: Condition, scene: Scene, obj: Objects, rng) -> list[tuple]:
    """Ellipsoids (kind, centre, semi-axes) where the pulses can return early from droplets."""
    L = scene.length
    clumps: list[tuple] = []
    if cond.name == "A":
        # exhaust condensation hanging where the vehicle stood, and mist over the largest puddle
        xs = cond.stop_at * L - min(2.0, 0.15 * L)  # exhaust drifts back from the stop
        y = cond.lanes[0]
        clumps.append((EXHAUST, np.array([xs, y, 0.75]), np.array([min(2.2, 0.3 * L), 1.2, 0.55])))
        px, py, ax, ay = obj.puddles[0]
        pz = scene.road_z(np.array([px]), np.array([py]))[0]
        clumps.append((WATER, np.array([px, py, pz + 0.2]), np.array([ax, ay, 0.18])))
    elif cond.name == "B":
        n = max(3, round(16 * L / 20))
        for _ in range(n):
            kind = EXHAUST if rng.random() < 0.5 else WATER
            c = np.array([rng.uniform(0.05, 0.95) * L, rng.uniform(-3.5, 3.5), 0.0])
            c[2] = scene.road_z(c[:1], c[1:2])[0] + rng.uniform(0.08, 0.9)
            clumps.append((kind, c, rng.uniform(0.12, 0.3, 3)))
    return clumps


def _add_outliers(cond: Condition, scene: Scene, obj: Objects, s: dict, rng):
    """Turn some pulses into outliers to reach the condition's share (Table 1).

    Clump outliers are extra first returns from droplets inside an ellipsoid in front of the
    surface (return 1 of 2; the surface is return 2 of 2). Near-surface outliers of C replace the
    surface return by one 1.5-6 cm above it along the beam; isolated ones are early returns
    0.2-1.5 m in front of the surface.
    """
    n = len(s["r"])
    n_arm = int(s["arm"].sum())
    share = cond.outlier_share
    # extra returns needed so that (arm + extra) / (n + extra) = share
    budget = max(0, round((share * n - n_arm) / (1 - share)))
    kinds = np.zeros(n, dtype=np.uint8)
    kinds[s["arm"]] = ARM
    extra_idx, extra_r, extra_kind = [], [], []
    clumps = _outlier_clumps(cond, scene, obj, rng)
    weights = cond.kind_weights
    total_w = sum(weights.values())
    for kind, w in weights.items():
        want = round(budget * w / total_w)
        if kind in (EXHAUST, WATER):
            t_in = np.full(n, np.inf)
            t_out = np.full(n, np.inf)
            for k, c, semi in clumps:
                if k != kind:
                    continue
                a, b = hit_ellipsoid(s["o"], s["d"], c, semi)
                closer = a < t_in
                t_in = np.where(closer, a, t_in)
                t_out = np.where(closer, b, t_out)
            pool = np.flatnonzero((t_in < s["r"] - 0.03) & (kinds == SURFACE))
            pick = rng.choice(pool, size=min(want, len(pool)), replace=False)
            far = np.minimum(t_out[pick], s["r"][pick] - 0.03)
            extra_idx.append(pick)
            extra_r.append(t_in[pick] + rng.uniform(0, 1, len(pick)) * (far - t_in[pick]))
            extra_kind.append(np.full(len(pick), kind, dtype=np.uint8))
        elif kind == NEAR_SURFACE:
            pool = np.flatnonzero((kinds == SURFACE) & (s["mat"] == ASPHALT))
            pick = rng.choice(pool, size=min(want, len(pool)), replace=False)
            dz = rng.uniform(0.015, 0.06, len(pick))
            s["r"][pick] -= dz / np.maximum(-s["d"][pick, 2], 0.2)
            kinds[pick] = NEAR_SURFACE
        elif kind == ISOLATED:
            pool = np.flatnonzero((kinds == SURFACE) & (s["r"] > 4.0))
            pick = rng.choice(pool, size=min(want, len(pool)), replace=False)
            extra_idx.append(pick)
            extra_r.append(s["r"][pick] - rng.uniform(0.2, 1.5, len(pick)))
            extra_kind.append(np.full(len(pick), kind, dtype=np.uint8))
    idx = np.concatenate(extra_idx) if extra_idx else np.zeros(0, dtype=int)
    idx, first = np.unique(idx, return_index=True)  # one extra return per pulse at most
    r_extra = np.concatenate(extra_r)[first] if len(idx) else np.zeros(0)
    k_extra = np.concatenate(extra_kind)[first] if len(idx) else np.zeros(0, dtype=np.uint8)
    p = s["o"][idx] + r_extra[:, None] * s["d"][idx]
    inside = ((p[:, 0] >= 0) & (p[:, 0] <= scene.length)
              & (p[:, 1] >= scene.crop_y[0]) & (p[:, 1] <= scene.crop_y[1]))
    return kinds, idx[inside], r_extra[inside], k_extra[inside]


def _intensity(r, cos_inc, material, rng) -> np.ndarray:
    """Intensity from reflectivity, incidence and range (a lidar-equation shape), 16 bit."""
    base = REFLECTIVITY[material] * np.clip(cos_inc, 0.05, 1.0) * np.minimum(1.0, (6.0 / r) ** 2)
    noisy = base * rng.normal(1.0, 0.08, len(r))
    return np.clip(noisy * 65535 / 0.9, 1, 65535).astype(np.uint16)


def simulate(condition: str, seed: int, scale: float = 1.0) -> SimulatedCloud:
    """Simulate one of the paper's clouds (A, B or C, Table 1).

    ``scale`` (0 < scale <= 1) shortens the strip (and the stop) by that factor, so the point
    count shrinks roughly in proportion. The result is a pure function of (condition, seed, scale).
    """
    if condition not in CONDITIONS:
        raise ValueError(f"condition must be one of A, B, C, got {condition!r}")
    if not 0.01 <= scale <= 1.0:
        raise ValueError(f"scale must be in [0.01, 1], got {scale!r}")
    cond = CONDITIONS[condition]
    rng = np.random.default_rng([seed, ord(condition)])
    scene = Scene(length=Scene().length * scale)
    obj = build_objects(scene, rng)
    s, traj = _survey(cond, scene, obj, rng)
    s = _operate_arm(cond, s)
    n = len(s["r"])
    # wet asphalt in the puddles is darker
    pts0 = s["o"] + s["r"][:, None] * s["d"]
    wet = (s["mat"] == ASPHALT) & in_puddle(pts0[:, 0], pts0[:, 1], obj)
    s["mat"] = np.where(wet, WET, s["mat"]).astype(np.int8)
    kinds, e_idx, e_r, e_kind = _add_outliers(cond, scene, obj, s, rng)

    r = s["r"] + rng.normal(0.0, scene.range_sigma, n)
    xyz = s["o"] + r[:, None] * s["d"]
    ground = np.isin(s["mat"], (ASPHALT, WET, CONCRETE)) & (kinds == SURFACE)
    xyz[ground, 2] += texture_height(xyz[ground, 0], xyz[ground, 1], obj)
    intensity = _intensity(r, s["cos"], s["mat"], rng)
    n_ret = np.ones(n, dtype=np.uint8)
    n_ret[e_idx] = 2
    ret = n_ret.copy()  # the surface return is the last one

    re = e_r + rng.normal(0.0, scene.range_sigma, len(e_idx))
    xyz_e = s["o"][e_idx] + re[:, None] * s["d"][e_idx]
    fog = np.full(len(e_idx), FOG, dtype=np.int8)
    int_e = _intensity(re, np.full(len(e_idx), 0.5), fog, rng)

    cat = np.concatenate
    gps = cat([s["t"], s["t"][e_idx]])
    src = cat([s["src"], s["src"][e_idx]])
    rn = cat([ret, np.ones(len(e_idx), dtype=np.uint8)])
    order = np.lexsort((rn, src, gps))
    kind_all = cat([kinds, e_kind]).astype(np.uint8)[order]
    return SimulatedCloud(
        xyz=cat([xyz, xyz_e])[order],
        gps_time=gps[order],
        point_source_id=src[order],
        intensity=cat([intensity, int_e])[order],
        return_number=rn[order],
        number_of_returns=cat([n_ret, np.full(len(e_idx), 2, dtype=np.uint8)])[order],
        scan_angle=cat([s["ang"], s["ang"][e_idx]]).astype(np.float32)[order],
        is_outlier=kind_all != SURFACE,
        kind=kind_all,
        trajectory=traj,
        condition=condition,
        seed=seed,
        scale=scale,
    )


# --------------------------------------------------------------------------- files

#: LAS 1.4 scan_angle unit for point formats 6-10.
SCAN_ANGLE_UNIT = 0.006


def stem(condition: str, seed: int) -> str:
    return f"{condition}_{seed}"


def write_simulation(cloud: SimulatedCloud, out_dir: Path) -> Path:
    """Write the LAS file, its truth and trajectory into ``out_dir``; returns the LAS path.

    Each file is written to a temporary name and renamed, so a reader never sees half a file.
    """
    out_dir = Path(out_dir)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ParameterError(f"cannot create output directory {out_dir}: {exc.strerror}") from exc
    base = out_dir / stem(cloud.condition, cloud.seed)
    las_path = base.with_suffix(".las")
    write_las_data(to_las(cloud), las_path)
    with atomic_path(base.with_suffix(".truth.npz")) as tmp:
        _write_truth(cloud, tmp)
    with atomic_path(base.with_suffix(".trajectory.txt")) as tmp:
        np.savetxt(tmp, cloud.trajectory, fmt="%.4f", header="time x y z")
    return las_path


def _write_truth(cloud: SimulatedCloud, path: Path) -> None:
    with open(path, "wb") as fh:
        np.savez_compressed(
            fh,
            is_outlier=cloud.is_outlier,
            kind=cloud.kind,
            kind_names=np.array(KIND_NAMES),
            condition=np.array(cloud.condition),
            seed=np.array(cloud.seed),
            scale=np.array(cloud.scale),
        )


def to_las(cloud: SimulatedCloud) -> laspy.LasData:
    """The cloud as LAS 1.4 point format 6 at 1 mm scale, classification 0."""
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales = np.array([0.001, 0.001, 0.001])
    header.offsets = np.floor(cloud.xyz.min(axis=0)) if len(cloud) else np.zeros(3)
    header.system_identifier = "lidar-outliers simulator"
    header.generating_software = f"simulate {cloud.condition} seed {cloud.seed}"
    las = laspy.LasData(header)
    las.x = cloud.xyz[:, 0]
    las.y = cloud.xyz[:, 1]
    las.z = cloud.xyz[:, 2]
    las.gps_time = cloud.gps_time
    las.point_source_id = cloud.point_source_id
    las.intensity = cloud.intensity
    las.return_number = cloud.return_number
    las.number_of_returns = cloud.number_of_returns
    las.scan_angle = np.round(cloud.scan_angle / SCAN_ANGLE_UNIT).astype(np.int16)
    las.classification = np.zeros(len(cloud), dtype=np.uint8)
    return las
