"""Outliers: how each kind arises physically, and how many of each a cloud gets.

Every outlier is a return a real scanner could record, placed by the beam that records it:

* ``exhaust_plume``: droplets of condensation or dust inside an ellipsoidal clump return part of
  a beam early (uniformly between where the beam enters the clump and where it leaves it or
  meets the surface). Clumps hang at a standstill (fed by the tailpipe while the vehicle stands,
  placed across a scan plane, so at a standstill they lie in one plane), drift with the wind for
  a few seconds, or trail behind the moving vehicle. The surface behind still answers (a second
  return) on a drawn share of the beams.
* ``water_multipath``: a beam meeting standing water is reflected specularly, meets the street
  (a car, a pole, a facade) and comes back the same way; the scanner times the whole path and
  places the return along the outgoing beam, i.e. at the mirror image of the object below the
  water surface. The diffuse return of the wet asphalt itself survives on a drawn share.
* ``glass_multipath``: the same about a window pane: the image of the street behind the glass.
  Beams that pass the glass return from the room behind it (real points).
* ``barrier_arm``: a barrier arm swinging between horizontal and vertical, in operation for a
  while; ``moving_object``: cars, cyclists and pedestrians in constant motion. Both are cast at
  each pulse's own instant, so each scanner sees them once, where they were at that moment.
* ``airborne``: rain, snow or insects (single returns along a beam, most near the scanner,
  also on beams into the open sky) and birds (small bodies flying through).
* ``mist``: mist over standing water and spray thrown up behind the wheels: returns at a height
  drawn in a band a few cm to about 1 m above the road, where the beam crosses that height.
* ``near_surface``: the ground return comes 1.5-6 cm high (range walk over a dusty film);
  ``isolated``: a single early return 0.2-1.5 m in front of a surface.

How many: the condition's share of outliers (Table 1) is split by the drawn mix. Kinds placed
by geometry (moving objects, mirrors) take what their geometry allows up to their part; kinds
that can go anywhere along a beam make up the rest, so the share is met exactly.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from lidar_outliers.tools.simulator import raycast as rc
from lidar_outliers.tools.simulator.bodies import Arm, Mover, body_kind
from lidar_outliers.tools.simulator.family import (
    AIRBORNE,
    ARM,
    ARM_PAINT,
    ASPHALT,
    CAR,
    EXHAUST,
    FOG,
    GLASS,
    GLASS_MP,
    GROUND,
    INTERIOR,
    ISOLATED,
    KIND_NAMES,
    MIST,
    MOVER,
    MOVING,
    NEAR_SURFACE,
    SURFACE,
    WATER,
    WET,
    Condition,
    Street,
    System,
)
from lidar_outliers.tools.simulator.survey import (
    Motion,
    cast_static,
    room_boxes,
    segment_bounds,
)

# --------------------------------------------------------------------------- the plan


@dataclass(frozen=True, eq=False)
class Clump:
    """An ellipsoid of droplets or dust: centre at t_ref (street frame, or the vehicle frame
    when ``attached``), semi-axes, drift (m/s) and the time it exists.

    A clump drawn before the survey has no centre yet (NaN): :func:`_place_clumps` puts it
    where a beam of the survey crossed the air above the road at a drawn height; its life is
    then ``life`` seconds around that beam's time (a standstill plume: the stop's interval).
    """

    centre: np.ndarray
    semi: np.ndarray
    drift: np.ndarray
    t_ref: float
    life: tuple[float, float]
    attached: bool = False
    moving_only: bool = False  # attached clumps that form only while driving
    standstill: bool = False  # fed by the tailpipe during the stop ``life``
    height: tuple[float, float] = (0.1, 1.2)  # of its centre above the road


@dataclass(frozen=True, eq=False)
class Patch:
    """Mist or spray over the road: an elliptic footprint (centre, semi-axes in x, y; in the
    vehicle frame when ``attached``) and the band of heights above the road it fills."""

    centre: np.ndarray
    semi: np.ndarray
    band: tuple[float, float]
    life: tuple[float, float]
    attached: bool = False


@dataclass(frozen=True, eq=False)
class OutlierPlan:
    """Everything drawn about one cloud's outliers (street frame, strip [0, L])."""

    mix: dict[int, float]
    puddles: np.ndarray  # (q, 4): cx, cy, semi x, semi y (placed after the survey)
    puddle_candidates: np.ndarray  # (m, 4) places the puddles are chosen from
    n_puddles: int
    puddle_mist: list[tuple[float, tuple[float, float]]]  # mist over the first puddles
    bodies: list[Mover | Arm]
    clumps: list[Clump]
    patches: list[Patch]
    behind_droplets: float  # share of droplet returns whose surface still answers
    water_direct: float  # share of water-mirror pulses that keep the wet asphalt's return
    glass_through: float  # share of window pulses that pass into the room
    near_band: tuple[float, float]
    isolated_band: tuple[float, float]
    rain_range: float  # mean distance of rain returns from the scanner

    def facts(self) -> dict:
        return {
            "mix": {KIND_NAMES[k]: round(w, 4) for k, w in self.mix.items()},
            "puddles": self.puddles.round(3).tolist(),
            "bodies": [_body_facts(b) for b in self.bodies],
            "clumps": len(self.clumps),
            "mist_patches": [{"band": list(p.band), "attached": p.attached}
                             for p in self.patches],
        }


def _body_facts(body: Mover | Arm) -> dict:
    if isinstance(body, Arm):
        return {"label": "barrier arm", "pivot": body.pivot.round(3).tolist(),
                "length": round(body.length, 3), "period": round(body.period, 3)}
    return {"label": body.label, "velocity": body.velocity.round(3).tolist(),
            "t_ref": round(body.t_ref, 4)}


def draw_plan(rng: np.random.Generator, cond: Condition, system: System, street: Street,
              motion: Motion, strip: float) -> OutlierPlan:
    """Draw the mix and every outlier source of one cloud."""
    mix = {k: float(rng.uniform(*r)) for k, r in cond.kinds.items()}
    total = sum(mix.values())
    mix = {k: w / total for k, w in mix.items()}
    hw = street.half_width
    in_strip = _in_strip_samples(motion, strip)

    # standing water: candidate places (most along the curbs, on the asphalt of the cut, not
    # under a parked car); where they go is settled once the survey shows which can mirror
    candidates = np.zeros((0, 4))
    n_puddles = 0
    if cond.wet:
        n_puddles = int(rng.integers(2, 7))
        rows = []
        for i in range(24):
            big = cond.name == "A" and i % 3 == 0
            semi = ([rng.uniform(1.5, 3.0), rng.uniform(0.8, 1.5)] if big
                    else [rng.uniform(0.5, 2.5), rng.uniform(0.3, 1.2)])
            for _ in range(20):
                if rng.random() < 0.6:  # water gathers along the curbs
                    y = rng.choice([-1.0, 1.0]) * (hw - rng.uniform(0.2, 1.2))
                else:
                    y = rng.uniform(-0.8, 0.8) * hw
                y = float(np.clip(y, max(-hw, street.crop_y[0]) + 0.2,
                                  min(hw, street.crop_y[1]) - 0.2))
                x = rng.uniform(0.0, strip)
                if not _under_a_car(street, x, y):
                    break
            rows.append([x, y, *semi])
        candidates = np.array(rows)

    bodies: list[Mover | Arm] = []
    if ARM in mix:
        bodies.append(_draw_arm(rng, system, street, motion, in_strip, strip))
    if MOVING in mix:
        for i in range(int(rng.integers(1, 4))):
            # the first one is on the road, in plain view
            bodies.append(_draw_mover(rng, system, street, motion, in_strip, strip,
                                      on_road=i == 0))
    if AIRBORNE in mix:
        for _ in range(int(rng.integers(1, 4))):
            bodies.append(_draw_bird(rng, system, street, motion, in_strip, strip))

    clumps: list[Clump] = []
    patches: list[Patch] = []
    if EXHAUST in mix:
        nan3 = np.full(3, np.nan)
        for ta, tb in motion.stops:
            semi = np.array([rng.uniform(0.4, 1.2), rng.uniform(0.3, 0.9), rng.uniform(0.25, 0.6)])
            clumps.append(Clump(nan3, semi, np.zeros(3), np.nan, (ta, tb), standstill=True,
                                height=(0.3, 1.3)))
        n_clumps = int(rng.integers(2, 7) if cond.name == "A" else rng.integers(8, 21))
        n_clumps = max(2, round(n_clumps * max(strip, 5.0) / 30.0))
        for _ in range(n_clumps):
            wind = rng.uniform(0, 1.5) * _unit2(rng)
            life = (-rng.uniform(1, 5), rng.uniform(1, 5))
            clumps.append(Clump(nan3, rng.uniform(0.1, 0.4, 3), wind, np.nan, life))
        if cond.cold and rng.random() < 0.5:
            offset = np.array([-system.vehicle_length / 2 - rng.uniform(0.6, 2.0),
                               system.tailpipe_left,
                               rng.uniform(0.4, 0.9) - system.reference_height])
            clumps.append(Clump(offset, np.array([rng.uniform(0.4, 1.5), 0.4, 0.3]),
                                np.zeros(3), 0.0, (-np.inf, np.inf), attached=True,
                                moving_only=True))
    puddle_mist = []
    if MIST in mix:  # mist over some of the puddles: (enlargement, band)
        puddle_mist = [(float(rng.uniform(1.0, 1.5)),
                        (float(rng.uniform(0.02, 0.08)), float(rng.uniform(0.2, 1.0))))
                       for _ in range(max(1, n_puddles // 2))]
        if rng.random() < 0.5:  # spray behind the rear wheels while driving
            band = (rng.uniform(0.02, 0.05), rng.uniform(0.3, 0.8))
            for s in (1.0, -1.0):
                patches.append(Patch(
                    np.array([-system.vehicle_length / 2 - rng.uniform(0.3, 1.0),
                              s * system.vehicle_width / 2]),
                    np.array([rng.uniform(0.5, 1.5), rng.uniform(0.3, 0.6)]), band,
                    (-np.inf, np.inf), attached=True))
        road = (max(-hw, street.crop_y[0]), min(hw, street.crop_y[1]))
        for _ in range(int(rng.integers(0, 4))):
            patches.append(Patch(np.array([rng.uniform(0, strip), rng.uniform(*road)]),
                                 np.array([rng.uniform(0.5, 2.5), rng.uniform(0.5, 2.0)]),
                                 (rng.uniform(0.02, 0.1), rng.uniform(0.2, 1.0)),
                                 (-np.inf, np.inf)))
    return OutlierPlan(
        mix=mix, puddles=np.zeros((0, 4)), puddle_candidates=candidates, n_puddles=n_puddles,
        puddle_mist=puddle_mist, bodies=bodies, clumps=clumps, patches=patches,
        behind_droplets=float(rng.uniform(0.3, 0.9)), water_direct=float(rng.uniform(0.2, 0.7)),
        glass_through=float(rng.uniform(0.4, 0.8)), near_band=(0.015, 0.06),
        isolated_band=(0.2, 1.5), rain_range=float(rng.uniform(3.0, 10.0)),
    )


def _unit2(rng: np.random.Generator) -> np.ndarray:
    a = rng.uniform(0, 2 * np.pi)
    return np.array([np.cos(a), np.sin(a), 0.0])


def _in_strip_samples(motion: Motion, strip: float) -> np.ndarray:
    """Pose samples with the vehicle over the strip (all samples if none)."""
    k = np.flatnonzero((motion.pos[:, 0] >= 0) & (motion.pos[:, 0] <= strip))
    return k if len(k) else np.arange(len(motion.t))


def _path_extent(motion: Motion, side: int, system: System) -> float:
    """How far toward ``side`` the vehicle's body reaches on any pass (|y| of its edge)."""
    return float(np.max(side * motion.pos[:, 1]) + system.vehicle_width / 2 + 0.4)


def _draw_arm(rng: np.random.Generator, system: System, street: Street, motion: Motion,
              in_strip: np.ndarray, strip: float) -> Arm:
    """A barrier arm on a post at the road edge, long enough to cross into the cut and short
    enough to clear the survey vehicle's path; where a scan plane sweeps it inside the strip."""
    hw = street.half_width
    best = None
    for side in ((1, -1) if rng.random() < 0.5 else (-1, 1)):
        length = float(np.clip(min(hw + 0.3 - _path_extent(motion, side, system),
                                   rng.uniform(3.0, 5.0)), 1.0, 5.0))
        post, tip = side * (hw + 0.3), side * (hw + 0.3 - length)
        lo, hi = min(post, tip), max(post, tip)
        overlap = min(hi, street.crop_y[1]) - max(lo, street.crop_y[0])
        if best is None or overlap > best[2]:
            best = (side, length, overlap, 0.5 * (max(lo, street.crop_y[0])
                                                  + min(hi, street.crop_y[1])))
    side, length, _, y_mid = best
    z = float(street.sidewalk_z(np.array([strip / 2]))[0]) + rng.uniform(0.8, 1.1)
    t_m, x = _in_view(rng, system, motion, in_strip, y_mid, z, strip)
    period = rng.uniform(6.0, 14.0)
    # the arm comes down about when the plane sweeps it
    phase = t_m - rng.uniform(-0.15, 0.15) * period
    return Arm(np.array([x, side * (hw + 0.3), z]), side, length,
               float(rng.uniform(0.035, 0.06)), float(period), float(phase))


def _in_view(rng: np.random.Generator, system: System, motion: Motion, in_strip: np.ndarray,
             y: float, z: float, strip: float) -> tuple[float, float]:
    """A moment of the drive and the x where a scan plane then crosses the line (y, z) inside
    the strip, within 25 m of its scanner: a body placed there is seen. Falls back to the
    middle of the strip at a moment over it."""
    pos, f, left, up = motion.at(motion.t)
    found_t, found_x = [], []
    for sc in system.scanners:
        n_v, _, _ = sc.plane_basis()
        n = n_v[0] * f + n_v[1] * left + n_v[2] * up
        o = pos + sc.offset[0] * f + sc.offset[1] * left + sc.offset[2] * up
        with np.errstate(divide="ignore", invalid="ignore"):
            x = o[:, 0] - (n[:, 1] * (y - o[:, 1]) + n[:, 2] * (z - o[:, 2])) / n[:, 0]
        near = np.hypot(x - o[:, 0], y - o[:, 1]) <= 25.0
        ok = (np.abs(n[:, 0]) > 0.2) & (x >= 0.0) & (x <= strip) & near
        found_t.append(motion.t[ok])
        found_x.append(x[ok])
    t_all, x_all = np.concatenate(found_t), np.concatenate(found_x)
    if not len(t_all):
        return float(motion.t[int(rng.choice(in_strip))]), strip / 2
    k = int(rng.integers(0, len(t_all)))
    return float(t_all[k]), float(x_all[k])


def _under_a_car(street: Street, x: float, y: float) -> bool:
    cars = street.boxes[street.box_mat == CAR]
    return bool(np.any((cars[:, 0] <= x) & (x <= cars[:, 3]) & (cars[:, 1] <= y)
                       & (y <= cars[:, 4])))


def _draw_mover(rng: np.random.Generator, system: System, street: Street, motion: Motion,
                in_strip: np.ndarray, strip: float, on_road: bool) -> Mover:
    """A car, cyclist or pedestrian crossing a scan plane inside the cut at a moment over the
    strip, clear of the survey vehicle's path (``on_road``: not on a sidewalk)."""
    hw = street.half_width
    lo_y, hi_y = street.crop_y
    lanes = motion.pos[in_strip, 1]
    clear = system.vehicle_width / 2 + 1.3

    def free(ys: np.ndarray, half: float) -> list[float]:
        return [float(y) for y in ys if np.min(np.abs(lanes - y)) >= clear + half
                and lo_y + 0.5 <= y <= hi_y - 0.5]

    label = str(rng.choice(["car", "cyclist", "pedestrian"], p=[0.45, 0.2, 0.35]))
    room = free(np.linspace(-hw + 1.2, hw - 1.2, 41), 1.0 if label == "car" else 0.4)
    if label != "pedestrian" and not room:
        label = "pedestrian"
    if label == "car":
        y = float(rng.choice(room))
        length, width, height = rng.uniform(3.8, 5.2), rng.uniform(1.7, 2.0), rng.uniform(1.4, 1.9)
        t_m, x = _in_view(rng, system, motion, in_strip, y, 1.0, strip)
        z = float(street.road_z(np.array([x]), np.array([y]))[0])
        vx = rng.choice([-1.0, 1.0]) * rng.uniform(3.0, 15.0)
        boxes = np.array([
            [x - length / 2, y - width / 2, z + 0.25, x + length / 2, y + width / 2, z + 0.95],
            [x - 0.3 * length, y - width / 2 + 0.1, z + 0.95, x + 0.3 * length,
             y + width / 2 - 0.1, z + height]])
        return Mover(MOVING, "car", np.array([vx, 0.0, street.grade * vx]), t_m, boxes=boxes)
    if label == "cyclist":
        y = float(rng.choice(room))
        t_m, x = _in_view(rng, system, motion, in_strip, y, 1.0, strip)
        z = float(street.road_z(np.array([x]), np.array([y]))[0])
        vx = rng.choice([-1.0, 1.0]) * rng.uniform(3.0, 7.0)
        boxes = np.array([[x - 0.9, y - 0.3, z, x + 0.9, y + 0.3, z + 1.7]])
        return Mover(MOVING, "cyclist", np.array([vx, 0.0, street.grade * vx]), t_m, boxes=boxes)
    # a pedestrian crossing the street or walking along it
    ys = np.linspace(lo_y + 0.4, hi_y - 0.4, 61)
    if on_road:
        ys = ys[np.abs(ys) <= hw - 0.4]
    clearance = np.min(np.abs(lanes[:, None] - ys), 0) if len(ys) else np.zeros(0)
    walkway = free(ys, 0.3) or ([float(y) for y in ys[np.argsort(-clearance)[:5]]]
                                if len(ys) else [float(hi_y - 0.4)])
    y = float(rng.choice(walkway))
    t_m, x = _in_view(rng, system, motion, in_strip, y, 1.0, strip)
    speed = rng.uniform(0.8, 1.8) * rng.choice([-1.0, 1.0])
    velocity = np.array([0.0, speed, 0.0]) if rng.random() < 0.5 else np.array([speed, 0, 0])
    z = float(street.ground_z(np.array([x]), np.array([y]))[0])
    return Mover(MOVING, "pedestrian", velocity, t_m,
                 cylinder=np.array([x, y, rng.uniform(0.2, 0.3), z, z + rng.uniform(1.5, 1.9)]))


def _draw_bird(rng: np.random.Generator, system: System, street: Street, motion: Motion,
               in_strip: np.ndarray, strip: float) -> Mover:
    """A bird flying through a scan plane over the cut, 2.5-8 m above the road."""
    y = float(rng.uniform(*street.crop_y))
    z = float(street.road_z(np.array([strip / 2]), np.array([0.0]))[0]) + rng.uniform(2.5, 8.0)
    t_m, x = _in_view(rng, system, motion, in_strip, y, z, strip)
    velocity = rng.uniform(4.0, 14.0) * _unit2(rng)
    semi = np.array([rng.uniform(0.08, 0.25), rng.uniform(0.08, 0.25), rng.uniform(0.05, 0.12)])
    return Mover(AIRBORNE, "bird", velocity, t_m, ellipsoid=np.array([x, y, z, *semi]))


# --------------------------------------------------------------------------- making them


@dataclass
class Records:
    """Returns of the cloud: the pulse (row of the survey arrays) and range of each, its kind,
    material, |cos incidence| and an intensity factor (multipath loses energy)."""

    ray: list[np.ndarray] = field(default_factory=list)
    r: list[np.ndarray] = field(default_factory=list)
    kind: list[np.ndarray] = field(default_factory=list)
    mat: list[np.ndarray] = field(default_factory=list)
    cos: list[np.ndarray] = field(default_factory=list)
    gain: list[np.ndarray] = field(default_factory=list)

    def add(self, ray, r, kind, mat, cos, gain=1.0) -> None:
        n = len(ray)
        self.ray.append(np.asarray(ray, dtype=np.int64))
        self.r.append(np.asarray(r, dtype=float))
        self.kind.append(np.broadcast_to(np.asarray(kind, dtype=np.uint8), (n,)).copy())
        self.mat.append(np.broadcast_to(np.asarray(mat, dtype=np.int8), (n,)).copy())
        self.cos.append(np.broadcast_to(np.asarray(cos, dtype=np.float32), (n,)).copy())
        self.gain.append(np.broadcast_to(np.asarray(gain, dtype=np.float32), (n,)).copy())

    def arrays(self) -> dict[str, np.ndarray]:
        names = ("ray", "r", "kind", "mat", "cos", "gain")
        return {k: np.concatenate(getattr(self, k)) for k in names}


def make_returns(s: dict[str, np.ndarray], plan: OutlierPlan, cond: Condition, system: System,
                 street: Street, motion: Motion, strip: float, rng: np.random.Generator
                 ) -> tuple[dict[str, np.ndarray], dict[str, int], OutlierPlan]:
    """Every return of the cloud from the survey's first hits ``s`` and the outlier plan.

    Returns the records (arrays of :class:`Records`), per kind name how many the mix asked
    for before the geometry had its say, and the plan with its puddles placed.
    """
    n = len(s["t"])
    real = np.isfinite(s["r"])
    est = cond.share / (1 - cond.share) * int(real.sum() + np.isfinite(s["r_dyn"]).sum())
    want = {k: int(round(w * est)) for k, w in plan.mix.items()}
    cut = _Cut(street, strip)
    recs = Records()
    taken = np.zeros(n, dtype=bool)  # pulses that already carry an outlier

    # moving bodies: each is present during one stretch of time that gives its part
    present = _present_bodies(s, plan, want, rng)
    rows = np.flatnonzero(present)
    kinds = np.array([body_kind(plan.bodies[j]) for j in s["dyn"][rows]], dtype=np.uint8)
    mats = np.where(kinds == ARM, ARM_PAINT, np.where(kinds == AIRBORNE, FOG, MOVER))
    recs.add(rows, s["r_dyn"][rows], kinds, mats, s["cos_dyn"][rows])
    taken[rows] = True
    base = real & ~present  # pulses whose return is the static street

    mat = s["mat"].copy()
    p0 = s["o"] + np.where(real, s["r"], 0.0)[:, None] * s["d"]
    asphalt = np.flatnonzero(base & (mat == ASPHALT))
    plan = _place_puddles(plan, s, asphalt, p0, street, system, cut, rng)
    plan = _place_clumps(plan, s, asphalt, street, system, motion, cut, rng)
    if len(plan.puddles):
        mat[base & (mat == ASPHALT) & _in_ellipses(p0[:, :2], plan.puddles)] = WET

    # windows: the street's mirror image behind the glass, the room behind it, or the pane
    panes = np.flatnonzero(base & (mat == GLASS))
    pool, m_r, m_mat, m_cos = _mirrors(s, panes, np.array([0.0, 1.0, 0.0]), street, system,
                                       cut, rng, min_drop=0.0)
    pick = _choose(rng, len(pool), want.get(GLASS_MP, 0))
    recs.add(pool[pick], m_r[pick], GLASS_MP, m_mat[pick], m_cos[pick], 0.5)
    taken[pool[pick]] = True
    rest = panes[~taken[panes]]
    room_r, room_ok = _room_returns(s, rest, street, cut)
    through = rng.random(len(rest)) < plan.glass_through
    into = through & room_ok
    recs.add(rest[into], room_r[into], SURFACE, INTERIOR, 0.7)
    recs.add(rest[~through], s["r"][rest[~through]], SURFACE, GLASS, s["cos"][rest[~through]],
             0.3)
    base[panes] = False

    # standing water: the street's mirror image below the road
    if WATER in plan.mix:
        wet = np.flatnonzero(base & (mat == WET))
        pool, m_r, m_mat, m_cos = _mirrors(s, wet, np.array([0.0, 0.0, 1.0]), street, system,
                                           cut, rng, min_drop=0.05)
        pick = _choose(rng, len(pool), want[WATER])
        recs.add(pool[pick], m_r[pick], WATER, m_mat[pick], m_cos[pick], 0.3)
        taken[pool[pick]] = True
        base[pool[pick][rng.random(len(pick)) >= plan.water_direct]] = False

    # near-surface returns replace ground returns
    if NEAR_SURFACE in plan.mix:
        ground = np.flatnonzero(base & np.isin(mat, GROUND))
        pick = ground[_choose(rng, len(ground), want[NEAR_SURFACE])]
        dz = rng.uniform(*plan.near_band, len(pick))
        recs.add(pick, s["r"][pick] - dz / np.maximum(-s["d"][pick, 2], 0.2), NEAR_SURFACE,
                 mat[pick], s["cos"][pick])
        base[pick] = False
        taken[pick] = True
    recs.add(np.flatnonzero(base), s["r"][base], SURFACE, mat[base], s["cos"][base])

    # returns along the beams make up the rest of the share: droplets, mist, rain, isolated
    along = [k for k in (EXHAUST, MIST, AIRBORNE, ISOLATED) if k in plan.mix]
    weights = np.array([plan.mix[k] for k in along])
    hidden = np.zeros(n, dtype=bool)
    for kind in along:
        # this kind's part of what is still missing (what earlier kinds could not place too)
        part = _missing(recs, cond.share, hidden) * plan.mix[kind] / weights.sum()
        weights = weights[1:]
        _along_beam(kind, int(round(part)), s, plan, street, system, motion, mat, base, taken,
                    hidden, cut, recs, rng)
    # what the geometry could not place, and the surfaces the droplets hid, go to any beam
    for _ in range(3):
        extra = int(round(_missing(recs, cond.share, hidden)))
        if extra <= 0:
            break
        _along_beam(ISOLATED, extra, s, plan, street, system, motion, mat, base, taken, hidden,
                    cut, recs, rng)
    out = recs.arrays()
    keep = ~((out["kind"] == SURFACE) & hidden[out["ray"]] & (out["mat"] != INTERIOR))
    return ({k: v[keep] for k, v in out.items()}, {KIND_NAMES[k]: v for k, v in want.items()},
            plan)


def _place_clumps(plan: OutlierPlan, s: dict[str, np.ndarray], asphalt: np.ndarray,
                  street: Street, system: System, motion: Motion, cut: _Cut,
                  rng: np.random.Generator) -> OutlierPlan:
    """Centre each clump drawn without a place where a beam of the survey crossed the air
    above the asphalt, inside the cut, at a height drawn in the clump's range: a clump there
    is seen.

    A drifting clump takes any such beam and lives its drawn seconds around it. A standstill
    plume takes a beam fired during its stop (the planes stand still, so the plume lies in
    them), among those crossing nearest the tailpipe.
    """
    clumps = []
    for c in plan.clumps:
        if c.attached or np.all(np.isfinite(c.centre)):
            clumps.append(c)
            continue
        rows = asphalt
        if c.standstill:
            rows = rows[(s["t"][rows] >= c.life[0]) & (s["t"][rows] <= c.life[1])]
        rows = rows[_choose(rng, len(rows), 2000)]
        h = rng.uniform(*c.height, len(rows))
        t_h, _ = rc.hit_road(s["o"][rows], s["d"][rows], street.half_width, street.crown,
                             street.grade, lift=h)
        ok = np.isfinite(t_h) & (t_h >= system.min_range + 0.2) & (t_h < s["r"][rows] - 0.1)
        points = s["o"][rows] + np.where(ok, t_h, 0.0)[:, None] * s["d"][rows]
        ok &= cut(points)
        rows, points = rows[ok], points[ok]
        if not len(rows):
            continue  # the survey never looked at this part of the air: no clump
        if c.standstill:
            t_mid = np.array([0.5 * (c.life[0] + c.life[1])])
            tail = motion.place(t_mid, np.array([-system.vehicle_length / 2 - 0.1,
                                                 system.tailpipe_left,
                                                 0.3 - system.reference_height]))[0]
            near = np.argsort(np.linalg.norm(points - tail, axis=1))[:10]
            k = int(near[rng.integers(0, len(near))])
            life = c.life
        else:
            k = int(rng.integers(0, len(rows)))
            life = (float(s["t"][rows[k]] + c.life[0]), float(s["t"][rows[k]] + c.life[1]))
        centre = points[k]
        semi = c.semi.copy()
        semi[2] = float(np.clip(semi[2], 0.1, max(0.1, centre[2] - float(street.road_z(
            centre[:1], centre[1:2])[0]) - 0.05)))  # the clump stays above the road
        clumps.append(replace(c, centre=centre, semi=semi, t_ref=float(s["t"][rows[k]]),
                              life=life))
    return replace(plan, clumps=clumps)


def _place_puddles(plan: OutlierPlan, s: dict[str, np.ndarray], asphalt: np.ndarray,
                   p0: np.ndarray, street: Street, system: System, cut: _Cut,
                   rng: np.random.Generator) -> OutlierPlan:
    """Put the puddles where water can show a mirror image inside the cut.

    A sample of the asphalt returns is reflected (:func:`_mirrors`); each candidate place is
    scored by the reflections that land in the cut from within it. The best place takes the
    first puddle (the large one of cloud A), the others are drawn among the places that score
    at all (any where none does). Mist patches then cover the first puddles.
    """
    cand = plan.puddle_candidates
    if not plan.n_puddles or not len(cand):
        return plan
    sample = asphalt[_choose(rng, len(asphalt), 20_000)]
    good, *_ = _mirrors(s, sample, np.array([0.0, 0.0, 1.0]), street, system, cut, rng,
                        min_drop=0.05)
    xy = p0[good, :2]
    score = np.array([int(_in_ellipses(xy, c[None, :]).sum()) for c in cand])
    best = int(np.argmax(score))
    rest = [i for i in np.flatnonzero(score > 0) if i != best] or [
        i for i in range(len(cand)) if i != best]
    others = [rest[i] for i in _choose(rng, len(rest), plan.n_puddles - 1)]
    puddles = cand[[best, *others]]
    patches = list(plan.patches)
    for (grow, band), (cx, cy, ax, ay) in zip(plan.puddle_mist, puddles, strict=False):
        patches.append(Patch(np.array([cx, cy]), np.array([ax, ay]) * grow, band,
                             (-np.inf, np.inf)))
    return replace(plan, puddles=puddles, patches=patches)


class _Cut:
    """The strip [0, L] x crop_y: which points fall inside."""

    def __init__(self, street: Street, strip: float) -> None:
        self.x = (0.0, strip)
        self.y = street.crop_y

    def __call__(self, p: np.ndarray) -> np.ndarray:
        return ((p[:, 0] >= self.x[0]) & (p[:, 0] <= self.x[1]) & (p[:, 1] >= self.y[0])
                & (p[:, 1] <= self.y[1]))


def _choose(rng: np.random.Generator, pool: int, k: int) -> np.ndarray:
    """k distinct indices of range(pool) (fewer if the pool is smaller)."""
    k = min(max(k, 0), pool)
    return rng.choice(pool, size=k, replace=False) if k else np.zeros(0, dtype=int)


def _missing(recs: Records, share: float, hidden: np.ndarray) -> float:
    """Outliers still needed so that outliers / all returns = share."""
    kinds = np.concatenate(recs.kind) if recs.kind else np.zeros(0, np.uint8)
    rays = np.concatenate(recs.ray) if recs.ray else np.zeros(0, np.int64)
    mats = np.concatenate(recs.mat) if recs.mat else np.zeros(0, np.int8)
    surface = kinds == SURFACE
    real = int(np.count_nonzero(surface & ~(hidden[rays] & (mats != INTERIOR))))
    out = int(np.count_nonzero(~surface))
    return share * real / (1 - share) - out


def _present_bodies(s: dict[str, np.ndarray], plan: OutlierPlan, want: dict[int, int],
                    rng: np.random.Generator) -> np.ndarray:
    """Pulses that return from a moving body: each body takes one stretch of its hits in time
    (the arm in operation, the car or bird in the cut) giving its part of its kind's share."""
    present = np.zeros(len(s["t"]), dtype=bool)
    bird_part = float(rng.uniform(0.2, 0.5))
    for kind in (ARM, MOVING, AIRBORNE):
        members = [j for j, b in enumerate(plan.bodies) if body_kind(b) == kind]
        if not members:
            continue
        budget = want.get(kind, 0) * (bird_part if kind == AIRBORNE else 1.0)
        parts = rng.dirichlet(np.ones(len(members))) * budget
        for j, part in zip(members, parts, strict=True):
            hit = np.flatnonzero((s["dyn"] == j) & np.isfinite(s["r_dyn"]))
            k = min(len(hit), int(round(part)))
            if k < 1:
                continue
            hit = hit[np.argsort(s["t"][hit], kind="stable")]
            start = int(rng.integers(0, len(hit) - k + 1))
            present[hit[start:start + k]] = True
    return present


def _in_ellipses(xy: np.ndarray, ell: np.ndarray) -> np.ndarray:
    out = np.zeros(len(xy), dtype=bool)
    for cx, cy, ax, ay in ell:
        out |= ((xy[:, 0] - cx) / ax) ** 2 + ((xy[:, 1] - cy) / ay) ** 2 <= 1.0
    return out


def _room_returns(s: dict[str, np.ndarray], rows: np.ndarray, street: Street, cut: _Cut
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Range of the return from the room behind each pane (rows), and whether it is in the cut."""
    r = np.full(len(rows), np.inf)
    if not len(rows):
        return r, np.zeros(0, dtype=bool)
    o, d = s["o"][rows], s["d"][rows]
    p = o + s["r"][rows, None] * d
    for fac in street.facades:
        on = np.flatnonzero(np.abs(p[:, 1] - fac.side * fac.y) < 1e-6)
        if len(on):
            lo, hi = room_boxes(street, fac, p[on, 0], p[on, 2])
            t_room, _ = rc.box_exit(p[on] + 1e-6 * d[on], d[on], lo, hi)
            r[on] = s["r"][rows[on]] + t_room
    q = o + np.where(np.isfinite(r), r, 0.0)[:, None] * d
    return r, np.isfinite(r) & cut(q)


def _mirrors(s: dict[str, np.ndarray], rows: np.ndarray, normal: np.ndarray, street: Street,
             system: System, cut: _Cut, rng: np.random.Generator, min_drop: float
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Specular paths: beams ``rows`` reflect about ``normal`` where they hit and return from
    the street; the scanner puts the return at the total path length along the outgoing beam.

    Returns the rows with a usable path, their apparent range, and the material and incidence
    of what the reflected beam met. ``min_drop``: the image must lie at least this far beyond
    the mirror (below the water) to be told apart from the mirror itself.
    """
    empty = (rows[:0], np.zeros(0), np.zeros(0, np.int8), np.zeros(0, np.float32))
    if not len(rows):
        return empty
    o, d = s["o"][rows], s["d"][rows]
    r1 = s["r"][rows]
    p1 = o + r1[:, None] * d
    d2 = rc.reflect(d, normal)
    # the image lies along the outgoing beam, so only paths that end before the beam leaves
    # the cut (and within range) can give one: the reflected beam is cast no further
    _, leave, _ = rc.slab(o, d, np.array([cut.x[0], cut.y[0], -np.inf]),
                          np.array([cut.x[1], cut.y[1], np.inf]))
    limit = np.minimum(system.max_range, leave) - r1
    hits = cast_static(p1, d2, street, segment_bounds(p1, d2, np.maximum(limit, 0.0)), rng)
    r2 = hits.t
    total = r1 + r2
    image = o + np.where(np.isfinite(total), total, 0.0)[:, None] * d
    drop = np.abs(np.where(np.isfinite(r2), r2, 0.0) * (d2 @ normal))
    ok = np.isfinite(r2) & (total <= system.max_range) & cut(image) & (drop >= min_drop)
    return rows[ok], total[ok], hits.mat[ok], hits.cos[ok]


def _clump_centres(c: Clump, t: np.ndarray, motion: Motion) -> np.ndarray:
    if c.attached:
        return motion.place(t, c.centre)
    return c.centre + np.outer(t - c.t_ref, c.drift)


def _along_beam(kind: int, k_want: int, s: dict[str, np.ndarray], plan: OutlierPlan,
                street: Street, system: System, motion: Motion, mat: np.ndarray,
                base: np.ndarray, taken: np.ndarray, hidden: np.ndarray, cut: _Cut,
                recs: Records, rng: np.random.Generator) -> int:
    """Add up to ``k_want`` returns of ``kind`` in front of surfaces (rain also in the open
    sky); returns how many were placed. A pulse carries at most one outlier."""
    if k_want <= 0:
        return 0
    free = ~taken & (np.isfinite(s["r"]) | s["sky"])
    surface_r = np.where(np.isfinite(s["r"]), s["r"], np.inf)
    if kind == EXHAUST:
        rows, r = _in_clumps(s, plan, system, motion, free, surface_r, rng)
    elif kind == MIST:
        rows, r = _in_mist(s, plan, street, system, motion, free & base & np.isin(mat, (ASPHALT,
                                                                                  WET)), rng)
    elif kind == AIRBORNE:
        rows = np.flatnonzero(free)
        # most backscatter comes from near the scanner: a truncated exponential in range
        far = np.minimum(surface_r[rows] - 0.3, 40.0)
        span = far - system.min_range
        rows, span = rows[span > 0], span[span > 0]
        u = rng.uniform(0, 1, len(rows))
        lam = plan.rain_range
        r = system.min_range - lam * np.log(1 - u * (1 - np.exp(-span / lam)))
    else:
        lo, hi = plan.isolated_band
        rows = np.flatnonzero(free & np.isfinite(s["r"])
                              & (surface_r > system.min_range + hi + 0.5))
        r = surface_r[rows] - rng.uniform(lo, hi, len(rows))
    p = s["o"][rows] + r[:, None] * s["d"][rows]
    inside = cut(p)
    rows, r = rows[inside], r[inside]
    pick = _choose(rng, len(rows), k_want)
    rows, r = rows[pick], r[pick]
    recs.add(rows, r, kind, FOG, 0.5)
    taken[rows] = True
    if kind in (EXHAUST, MIST):  # a dense clump can swallow the pulse: the surface is lost
        hidden[rows[rng.random(len(rows)) >= plan.behind_droplets]] = True
    return len(rows)


def _in_clumps(s: dict[str, np.ndarray], plan: OutlierPlan, system: System, motion: Motion,
               free: np.ndarray, surface_r: np.ndarray, rng: np.random.Generator
               ) -> tuple[np.ndarray, np.ndarray]:
    """Pulses crossing a clump while it exists, and a range drawn uniformly in the crossing
    (before the surface the beam meets)."""
    start = np.full(len(free), np.inf)
    stop = np.full(len(free), np.inf)
    for c in plan.clumps:
        rows = np.flatnonzero(free & (s["t"] >= c.life[0]) & (s["t"] <= c.life[1]))
        if c.moving_only and len(rows):
            rows = rows[np.interp(s["t"][rows], motion.t, motion.speed) > 0.5]
        if not len(rows):
            continue
        t_in, t_out = rc.hit_ellipsoid(s["o"][rows], s["d"][rows],
                                       _clump_centres(c, s["t"][rows], motion), c.semi)
        t_in = np.maximum(t_in, system.min_range)
        end = np.minimum(t_out, surface_r[rows] - 0.05)
        closer = (t_in < end) & (t_in < start[rows])
        start[rows[closer]], stop[rows[closer]] = t_in[closer], end[closer]
    rows = np.flatnonzero(np.isfinite(start))
    return rows, start[rows] + rng.uniform(0, 1, len(rows)) * (stop[rows] - start[rows])


def _in_mist(s: dict[str, np.ndarray], plan: OutlierPlan, street: Street, system: System,
             motion: Motion, ground: np.ndarray, rng: np.random.Generator
             ) -> tuple[np.ndarray, np.ndarray]:
    """Pulses that meet the road under a mist patch, and where they cross a height drawn in
    the patch's band above the road (solved exactly on the road surface raised by it)."""
    rows_all, r_all = [], []
    for patch in plan.patches:
        rows = np.flatnonzero(ground & (s["t"] >= patch.life[0]) & (s["t"] <= patch.life[1]))
        if patch.attached and len(rows):
            rows = rows[np.interp(s["t"][rows], motion.t, motion.speed) > 2.0]
        if not len(rows):
            continue
        if patch.attached:
            centre = motion.place(s["t"][rows], np.array([*patch.centre,
                                                          -system.reference_height]))[:, :2]
        else:
            centre = np.broadcast_to(patch.centre, (len(rows), 2))
        p = s["o"][rows] + s["r"][rows, None] * s["d"][rows]
        inside = np.sum(((p[:, :2] - centre) / patch.semi) ** 2, axis=1) <= 1.0
        rows, centre = rows[inside], centre[inside]
        h = rng.uniform(*patch.band, len(rows))
        t_h, _ = rc.hit_road(s["o"][rows], s["d"][rows], street.half_width, street.crown,
                             street.grade, lift=h)
        q = s["o"][rows] + np.where(np.isfinite(t_h), t_h, 0.0)[:, None] * s["d"][rows]
        ok = (np.isfinite(t_h) & (t_h < s["r"][rows] - 0.01) & (t_h >= system.min_range)
              & (np.sum(((q[:, :2] - centre) / (1.2 * patch.semi)) ** 2, axis=1) <= 1.0))
        rows_all.append(rows[ok])
        r_all.append(t_h[ok])
    if not rows_all:
        return np.zeros(0, dtype=np.int64), np.zeros(0)
    rows, first = np.unique(np.concatenate(rows_all), return_index=True)
    return rows, np.concatenate(r_all)[first]
