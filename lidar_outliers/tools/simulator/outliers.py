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

from dataclasses import dataclass, field

import numpy as np

from lidar_outliers.tools.simulator import raycast as rc
from lidar_outliers.tools.simulator.bodies import Arm, Mover, body_kind
from lidar_outliers.tools.simulator.family import (
    AIRBORNE,
    ARM,
    ARM_PAINT,
    ASPHALT,
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
    scanner_rays,
    segment_bounds,
)

# --------------------------------------------------------------------------- the plan


@dataclass(frozen=True, eq=False)
class Clump:
    """An ellipsoid of droplets or dust: centre at t_ref (street frame, or the vehicle frame
    when ``attached``), semi-axes, drift (m/s) and the time it exists."""

    centre: np.ndarray
    semi: np.ndarray
    drift: np.ndarray
    t_ref: float
    life: tuple[float, float]
    attached: bool = False
    moving_only: bool = False  # attached clumps that form only while driving


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
    puddles: np.ndarray  # (q, 4): cx, cy, semi x, semi y
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

    puddles = np.zeros((0, 4))
    if cond.wet:
        n = int(rng.integers(2, 7))
        rows = []
        for i in range(n):
            big = cond.name == "A" and i == 0
            semi = ([rng.uniform(1.5, 3.0), rng.uniform(0.8, 1.5)] if big
                    else [rng.uniform(0.5, 2.5), rng.uniform(0.3, 1.2)])
            if rng.random() < 0.6:  # water gathers along the curbs
                y = rng.choice([-1.0, 1.0]) * (hw - rng.uniform(0.2, 1.2))
            else:
                y = rng.uniform(-0.8, 0.8) * hw
            rows.append([rng.uniform(0.0, strip), y, *semi])
        puddles = np.array(rows)

    bodies: list[Mover | Arm] = []
    if ARM in mix:
        bodies.append(_draw_arm(rng, system, street, motion, strip))
    if MOVING in mix:
        for _ in range(int(rng.integers(1, 4))):
            bodies.append(_draw_mover(rng, system, street, motion, in_strip))
    if AIRBORNE in mix:
        for _ in range(int(rng.integers(1, 4))):
            bodies.append(_draw_bird(rng, street, motion, in_strip, strip))

    clumps: list[Clump] = []
    patches: list[Patch] = []
    if EXHAUST in mix:
        for ta, tb in motion.stops:
            clumps.append(_standstill_plume(rng, system, street, motion, ta, tb, strip))
        n_clumps = int(rng.integers(2, 7) if cond.name == "A" else rng.integers(8, 21))
        n_clumps = max(2, round(n_clumps * max(strip, 5.0) / 30.0))
        for _ in range(n_clumps):
            k = int(rng.choice(in_strip))
            c = np.array([rng.uniform(0, strip), rng.uniform(*street.crop_y), 0.0])
            c[1] = np.clip(c[1], -hw, hw)
            c[2] = float(street.road_z(c[:1], c[1:2])[0]) + rng.uniform(0.1, 1.2)
            wind = rng.uniform(0, 1.5) * _unit2(rng)
            life = (motion.t[k] - rng.uniform(1, 5), motion.t[k] + rng.uniform(1, 5))
            clumps.append(Clump(c, rng.uniform(0.1, 0.4, 3), wind, float(motion.t[k]), life))
        if cond.cold and rng.random() < 0.5:
            offset = np.array([-system.vehicle_length / 2 - rng.uniform(0.6, 2.0),
                               system.tailpipe_left,
                               rng.uniform(0.4, 0.9) - system.reference_height])
            clumps.append(Clump(offset, np.array([rng.uniform(0.4, 1.5), 0.4, 0.3]),
                                np.zeros(3), 0.0, (-np.inf, np.inf), attached=True,
                                moving_only=True))
    if MIST in mix:
        for cx, cy, ax, ay in puddles[: max(1, len(puddles) // 2)]:
            patches.append(Patch(np.array([cx, cy]), np.array([ax, ay]) * rng.uniform(1.0, 1.5),
                                 (rng.uniform(0.02, 0.08), rng.uniform(0.2, 1.0)),
                                 (-np.inf, np.inf)))
        if rng.random() < 0.5:  # spray behind the rear wheels while driving
            band = (rng.uniform(0.02, 0.05), rng.uniform(0.3, 0.8))
            for s in (1.0, -1.0):
                patches.append(Patch(
                    np.array([-system.vehicle_length / 2 - rng.uniform(0.3, 1.0),
                              s * system.vehicle_width / 2]),
                    np.array([rng.uniform(0.5, 1.5), rng.uniform(0.3, 0.6)]), band,
                    (-np.inf, np.inf), attached=True))
        for _ in range(int(rng.integers(0, 4))):
            patches.append(Patch(np.array([rng.uniform(0, strip), rng.uniform(-0.8, 0.8) * hw]),
                                 np.array([rng.uniform(0.5, 2.5), rng.uniform(0.5, 2.0)]),
                                 (rng.uniform(0.02, 0.1), rng.uniform(0.2, 1.0)),
                                 (-np.inf, np.inf)))
    return OutlierPlan(
        mix=mix, puddles=puddles, bodies=bodies, clumps=clumps, patches=patches,
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
              strip: float) -> Arm:
    hw = street.half_width
    best = None
    for side in ((1, -1) if rng.random() < 0.5 else (-1, 1)):
        length = hw + 0.3 - _path_extent(motion, side, system)
        if best is None or length > best[1]:
            best = (side, length)
        if length >= 1.5:
            break
    side, length = best[0], float(np.clip(min(best[1], rng.uniform(3.0, 5.0)), 1.0, 5.0))
    x = rng.uniform(0.1, 0.9) * strip
    pivot = np.array([x, side * (hw + 0.3), 0.0])
    pivot[2] = float(street.sidewalk_z(pivot[:1])[0]) + rng.uniform(0.8, 1.1)
    period = rng.uniform(6.0, 14.0)
    return Arm(pivot, side, length, float(rng.uniform(0.035, 0.06)), float(period),
               float(rng.uniform(0, period)))


def _draw_mover(rng: np.random.Generator, system: System, street: Street, motion: Motion,
                in_strip: np.ndarray) -> Mover:
    """A car, cyclist or pedestrian that is near the vehicle at a moment over the strip."""
    hw = street.half_width
    k = int(rng.choice(in_strip))
    t_m = float(motion.t[k])
    xv, yv = motion.pos[k, 0], motion.pos[k, 1]
    lo_y, hi_y = street.crop_y
    label = str(rng.choice(["car", "cyclist", "pedestrian"], p=[0.45, 0.2, 0.35]))
    clear = system.vehicle_width / 2 + 1.3
    if label in ("car", "cyclist"):
        half = 1.0 if label == "car" else 0.4
        room = [y for y in np.linspace(-hw + half + 0.2, hw - half - 0.2, 41)
                if abs(y - yv) >= clear + half and lo_y + 0.5 <= y <= hi_y - 0.5]
        if not room:
            label = "pedestrian"
    if label == "car":
        y = float(rng.choice(room))
        length, width, height = rng.uniform(3.8, 5.2), rng.uniform(1.7, 2.0), rng.uniform(1.4, 1.9)
        x = xv + rng.uniform(-6, 6)
        z = float(street.road_z(np.array([x]), np.array([y]))[0])
        vx = rng.choice([-1.0, 1.0]) * rng.uniform(3.0, 15.0)
        boxes = np.array([
            [x - length / 2, y - width / 2, z + 0.25, x + length / 2, y + width / 2, z + 0.95],
            [x - 0.3 * length, y - width / 2 + 0.1, z + 0.95, x + 0.3 * length,
             y + width / 2 - 0.1, z + height]])
        return Mover(MOVING, "car", np.array([vx, 0.0, street.grade * vx]), t_m, boxes=boxes)
    if label == "cyclist":
        y = float(rng.choice(room))
        x = xv + rng.uniform(-6, 6)
        z = float(street.road_z(np.array([x]), np.array([y]))[0])
        vx = rng.choice([-1.0, 1.0]) * rng.uniform(3.0, 7.0)
        boxes = np.array([[x - 0.9, y - 0.3, z, x + 0.9, y + 0.3, z + 1.7]])
        return Mover(MOVING, "cyclist", np.array([vx, 0.0, street.grade * vx]), t_m, boxes=boxes)
    # a pedestrian crossing behind the vehicle, or walking along the cut
    heading = float(np.cos(motion.heading[k]))
    speed = rng.uniform(0.8, 1.8)
    radius, height = rng.uniform(0.2, 0.3), rng.uniform(1.5, 1.9)
    if rng.random() < 0.5:
        x = xv - np.sign(heading or 1.0) * rng.uniform(3.0, 10.0)
        y = np.clip(yv + rng.uniform(-4, 4), lo_y + 0.5, hi_y - 0.5)
        velocity = np.array([0.0, rng.choice([-1.0, 1.0]) * speed, 0.0])
    else:
        choices = [y for y in np.linspace(lo_y + 0.4, hi_y - 0.4, 41) if abs(y - yv) >= clear]
        y = float(rng.choice(choices)) if choices else float(hi_y - 0.4)
        x = xv + rng.uniform(-8, 8)
        velocity = np.array([rng.choice([-1.0, 1.0]) * speed, 0.0, 0.0])
    z = float(street.ground_z(np.array([x]), np.array([y]))[0])
    return Mover(MOVING, "pedestrian", velocity, t_m,
                 cylinder=np.array([x, y, radius, z, z + height]))


def _draw_bird(rng: np.random.Generator, street: Street, motion: Motion, in_strip: np.ndarray,
               strip: float) -> Mover:
    k = int(rng.choice(in_strip))
    c = np.array([rng.uniform(0, strip), rng.uniform(*street.crop_y), 0.0])
    c[2] = float(street.road_z(c[:1], np.array([0.0]))[0]) + rng.uniform(2.5, 8.0)
    velocity = rng.uniform(4.0, 14.0) * _unit2(rng)
    semi = np.array([rng.uniform(0.08, 0.25), rng.uniform(0.08, 0.25), rng.uniform(0.05, 0.12)])
    return Mover(AIRBORNE, "bird", velocity, float(motion.t[k]),
                 ellipsoid=np.concatenate([c, semi]))


def _standstill_plume(rng: np.random.Generator, system: System, street: Street, motion: Motion,
                      ta: float, tb: float, strip: float) -> Clump:
    """A clump fed by the tailpipe while the vehicle stands, centred on one scanner's plane
    (the scanners keep slicing the same plane), within reach of its beam, inside the cut where
    one is possible."""
    t_mid = np.array([0.5 * (ta + tb)])
    pos, f, left, up = motion.at(t_mid)
    tail = (pos[0] + (-system.vehicle_length / 2 - 0.1) * f[0] + system.tailpipe_left * left[0]
            + (0.3 - system.reference_height) * up[0])
    cands = []
    for sc in system.scanners:
        phi_grid = np.linspace(-np.pi, np.pi, 721)
        # fire the plane once (times at which the mirror points at each phi)
        period = 1.0 / sc.scan_hz
        t = t_mid[0] + np.mod((phi_grid - sc.phase) * sc.spin / (2 * np.pi), 1.0) * period
        t = np.minimum(t, tb)
        o, d, _, blocked = scanner_rays(motion, system, sc, t)
        for rho in np.arange(system.min_range + 0.4, system.min_range + 4.0, 0.2):
            q = o + rho * d
            h = q[:, 2] - street.road_z(q[:, 0], q[:, 1])
            ok = ~blocked & (h >= 0.3) & (h <= 1.3)
            inside = ok & (q[:, 0] >= 0) & (q[:, 0] <= strip) & (q[:, 1] >= street.crop_y[0]) \
                & (q[:, 1] <= street.crop_y[1])
            for j in np.flatnonzero(ok):
                cands.append((not inside[j], float(np.linalg.norm(q[j] - tail)), q[j]))
    cands.sort(key=lambda c: (c[0], c[1]))
    pick = cands[int(rng.integers(0, min(10, len(cands))))][2] if cands else tail
    semi = np.array([rng.uniform(0.4, 1.2), rng.uniform(0.3, 0.9), rng.uniform(0.25, 0.6)])
    semi[2] = min(semi[2], pick[2] - float(street.road_z(pick[:1], pick[1:2])[0]) - 0.05)
    semi[2] = max(semi[2], 0.15)
    return Clump(np.asarray(pick, dtype=float), semi, np.zeros(3), float(t_mid[0]), (ta, tb))


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
                 ) -> tuple[dict[str, np.ndarray], dict[str, int]]:
    """Every return of the cloud from the survey's first hits ``s`` and the outlier plan.

    Returns the records (arrays of :class:`Records`) and, per kind name, how many the mix
    asked for before the geometry had its say.
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
    if len(plan.puddles):
        p0 = s["o"] + np.where(real, s["r"], 0.0)[:, None] * s["d"]
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
    return {k: v[keep] for k, v in out.items()}, {KIND_NAMES[k]: v for k, v in want.items()}


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
    limit = system.max_range - r1
    hits = cast_static(p1, d2, street, segment_bounds(p1, d2, limit), rng)
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
