"""The survey: the vehicle's motion, every pulse of every scanner, and its first return.

The vehicle follows its plan (passes, lanes, weave, stops) on the street's surface: the
reference point rides ``reference_height`` above the road along the body's up axis, and the
body pitches and rolls with the road's grade and crown. Each scanner fires at its pulse rate
while its mirror turns at its scan rate; a pulse leaves the scanner's lever arm along the
mirror direction, both carried into the street frame by the vehicle's attitude at that instant.
Pulses are cast analytically (:mod:`.raycast`) against the static street and the moving objects;
only pulses whose scan plane can reach the cut are fired, and only returns inside the cut are
kept (plus a sparse sample of beams into the open sky, where rain can still answer).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from lidar_outliers.tools.simulator import raycast as rc
from lidar_outliers.tools.simulator.bodies import Arm, Mover, cast_dynamic
from lidar_outliers.tools.simulator.family import (
    ASPHALT,
    CONCRETE,
    FOLIAGE,
    GLASS,
    LID,
    POSE_HZ,
    STREET_MARGIN,
    WALL,
    DrivePlan,
    Facade,
    Scanner,
    Street,
    System,
)

#: Pulses per casting batch (bounds the working memory: about 1 kB per pulse).
CHUNK = 1 << 16
#: Share of the beams into the open sky that are kept as candidates for rain returns.
SKY_SAMPLE = 0.03


# --------------------------------------------------------------------------- motion


def vehicle_axes(roll: np.ndarray, pitch: np.ndarray, heading: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Forward, left and up unit vectors (each (n, 3)) of a body at the given attitude.

    Heading turns about z (0: +x), pitch raises the nose, roll raises the left side.
    """
    ch, sh = np.cos(heading), np.sin(heading)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cr, sr = np.cos(roll), np.sin(roll)
    f = np.column_stack([ch * cp, sh * cp, sp])
    l0 = np.column_stack([-sh, ch, np.zeros_like(ch)])
    u0 = np.column_stack([-sp * ch, -sp * sh, cp])
    left = cr[:, None] * l0 + sr[:, None] * u0
    up = -sr[:, None] * l0 + cr[:, None] * u0
    return f, left, up


@dataclass
class Motion:
    """Pose samples at POSE_HZ while the vehicle drives its passes (street frame).

    ``t`` (m,) GPS s; ``pos`` (m, 3) the reference point; ``roll``, ``pitch``, ``heading`` (m,)
    radians (heading unwrapped within a pass); ``speed`` (m,) m/s; ``pass_id`` (m,);
    ``passes`` [(t0, t1)] of each pass; ``stops`` [(t0, t1)] of each standstill.
    """

    t: np.ndarray
    pos: np.ndarray
    roll: np.ndarray
    pitch: np.ndarray
    heading: np.ndarray
    speed: np.ndarray
    pass_id: np.ndarray
    passes: list[tuple[float, float]]
    stops: list[tuple[float, float]]

    def at(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Reference point (n, 3) and forward, left, up axes (n, 3 each) at times t."""
        pos = np.column_stack([np.interp(t, self.t, self.pos[:, k]) for k in range(3)])
        f, left, up = vehicle_axes(np.interp(t, self.t, self.roll),
                                   np.interp(t, self.t, self.pitch),
                                   np.interp(t, self.t, self.heading))
        return pos, f, left, up

    def place(self, t: np.ndarray, offset: np.ndarray) -> np.ndarray:
        """World position (n, 3) of a point fixed in the vehicle frame at ``offset`` (3,)."""
        pos, f, left, up = self.at(t)
        return pos + offset[0] * f + offset[1] * left + offset[2] * up


def lateral(x: np.ndarray, lane: float, weave: tuple[float, float, float],
            change: tuple[float, float, float], strip: float) -> tuple[np.ndarray, np.ndarray]:
    """y of the path and dy/dx at x: the lane, a gentle weave and an optional lane change."""
    amp, wl, ph = weave
    shift, centre, length = change
    k = 2 * np.pi / wl
    y = lane + amp * np.sin(k * x + ph)
    dy = amp * k * np.cos(k * x + ph)
    if shift:
        s = np.tanh(2.0 * (x - centre * strip) / length)
        y = y + shift * 0.5 * (1 + s)
        dy = dy + shift * (1 - s**2) / length
    return y, dy


def build_motion(plan: DrivePlan, street: Street, system: System, scale: float,
                 margin: float, extent: float) -> Motion:
    """Pose samples of every pass over the strip [0, L] (L = plan.strip x scale).

    Each pass runs from ``margin`` before the strip to ``margin`` after ``extent`` (>= L, the
    street that may still be cut), forward along its lane with the weave and lane change of its
    plan. Speeds stay real; stop lengths and braking distances shrink with ``scale``
    (deceleration / scale, stop seconds x scale), so the part of the drive over the strip is
    the full-size drive shrunk in space and time, and the point count follows ``scale``. The
    body pitches and rolls with the road's grade and crown under it.
    """
    strip = plan.strip * scale
    rows: list[np.ndarray] = []
    passes, stops = [], []
    t0 = plan.start
    for i, p in enumerate(plan.passes):
        xa, xb = -margin, extent + margin
        if p.direction < 0:
            xa, xb = xb, xa
        x = np.linspace(xa, xb, int(abs(xb - xa) / 0.05) + 2)
        y, dy = lateral(x, p.lane, p.weave, p.lane_change, strip)
        ds = np.sqrt(1 + dy**2)
        sigma = np.concatenate([[0.0], np.cumsum(0.5 * (ds[1:] + ds[:-1]) * np.abs(np.diff(x)))])
        my_stops = sorted((s for s in plan.stops if s.pass_index == i), key=lambda s: (
            s.fraction if p.direction > 0 else -s.fraction))
        # the vehicle stands so that its scan planes' footprint is at the stop's place
        st_x = [np.clip(s.fraction * strip - p.direction * plan.footprint, -margin, strip + margin)
                for s in my_stops]
        st_sigma = [float(np.interp(sx, x[::p.direction], sigma[::p.direction])) for sx in st_x]
        st_decel = [s.decel / scale for s in my_stops]
        st_wait = [s.seconds * scale for s in my_stops]
        t_rel, s_knots, dwell = _speed_profile(sigma[-1], p.speed, st_sigma, st_decel, st_wait)
        for (ta, tb) in dwell:
            stops.append((t0 + ta, t0 + tb))
        tk = np.arange(0.0, t_rel[-1], 1.0 / POSE_HZ)
        tk = np.append(tk, t_rel[-1])
        sk = np.interp(tk, t_rel, s_knots)
        speed = np.gradient(sk, tk)
        xs = np.interp(sk, sigma, x)
        ys, dys = lateral(xs, p.lane, p.weave, p.lane_change, strip)
        heading = np.arctan2(p.direction * dys, float(p.direction) * np.ones_like(dys))
        heading = np.unwrap(heading)
        gz = street.grade
        sy = -2 * street.crown / street.half_width**2 * ys  # dz/dy of the crowned road
        ch, sh = np.cos(heading), np.sin(heading)
        pitch = np.arctan(gz * ch + sy * sh)
        roll = np.arctan(-gz * sh + sy * ch)
        _, _, up = vehicle_axes(roll, pitch, heading)
        ground = np.column_stack([xs, ys, street.road_z(xs, ys)])
        pos = ground + system.reference_height * up
        rows.append(np.column_stack([t0 + tk, pos, roll, pitch, heading, speed,
                                     np.full(len(tk), i)]))
        passes.append((t0 + tk[0], t0 + tk[-1]))
        if i < len(plan.gaps):
            t0 = t0 + tk[-1] + plan.gaps[i]
    a = np.concatenate(rows)
    return Motion(a[:, 0], a[:, 1:4], a[:, 4], a[:, 5], a[:, 6], a[:, 7],
                  a[:, 8].astype(int), passes, stops)


def _speed_profile(length: float, speed: float, stops: list[float], decel: list[float],
                   wait: list[float]) -> tuple[np.ndarray, np.ndarray, list[tuple[float, float]]]:
    """Time and arc-length knots of a drive at ``speed`` that brakes to each stop and pulls
    away at the same rate; and the (start, end) time of each standstill.

    Between knots v^2 is linear in arc length (cruise or constant acceleration), so each
    interval's time is exactly 2 ds / (v1 + v2).
    """
    grid = [np.linspace(0.0, length, max(int(length / 0.05), 2) + 1)]
    for s, a in zip(stops, decel, strict=True):
        reach = speed**2 / (2 * a)
        near = s + np.concatenate([-np.geomspace(reach, reach * 1e-6, 200), [0.0],
                                   np.geomspace(reach * 1e-6, reach, 200)])
        grid.append(np.clip(near, 0.0, length))
    s_grid = np.unique(np.concatenate(grid))
    v2 = np.full(len(s_grid), speed**2)
    for s, a in zip(stops, decel, strict=True):
        v2 = np.minimum(v2, 2 * a * np.abs(s_grid - s))
    v = np.sqrt(v2)
    with np.errstate(divide="ignore"):
        dt = 2 * np.diff(s_grid) / (v[1:] + v[:-1])
    t = np.concatenate([[0.0], np.cumsum(dt)])
    # each standstill: the knot at the stop is repeated, the later copy ``wait`` seconds on
    at = [int(np.argmin(np.abs(s_grid - s))) for s in stops]
    shift = np.zeros(len(s_grid))
    dwell = []
    for j, w in zip(at, wait, strict=True):
        dwell.append((float(t[j] + shift[j]), float(t[j] + shift[j] + w)))
        shift[j + 1:] += w
    t = t + shift
    ends = [b for _, b in dwell]
    t = np.insert(t, [j + 1 for j in at], ends)
    s_grid = np.insert(s_grid, [j + 1 for j in at], s_grid[at])
    return t, s_grid, dwell


def reach_margin(system: System, street: Street) -> float:
    """How far (m, along the street) a scan plane can reach the cut from the vehicle."""
    wide = max(abs(street.crop_y[0]), abs(street.crop_y[1])) + street.half_width
    reach = 0.0
    for sc in system.scanners:
        yaw, pitch = np.deg2rad(sc.yaw_deg), np.deg2rad(sc.pitch_deg)
        reach = max(reach, abs(np.tan(yaw)) * wide / max(np.cos(pitch), 0.3)
                    + abs(np.tan(pitch)) * (street.top + 3.0) + abs(sc.offset[0]))
    return float(np.clip(reach + 5.0, 10.0, STREET_MARGIN - 5.0))


# --------------------------------------------------------------------------- pulses


def mirror_angle(sc: Scanner, t: np.ndarray) -> np.ndarray:
    """Mirror angle (radians in [-pi, pi)) from the plane's downward direction at times t."""
    turns = np.mod(sc.scan_hz * t, 1.0)  # fractional turns keep the precision at GPS times
    phi = sc.phase + sc.spin * 2 * np.pi * turns
    return np.mod(phi + np.pi, 2 * np.pi) - np.pi


def scanner_rays(motion: Motion, system: System, sc: Scanner, t: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Origins (n, 3), unit directions (n, 3), mirror angles (n,) radians and whether the
    vehicle's own body blocks the beam (n,) for pulses of scanner ``sc`` at times t."""
    phi = mirror_angle(sc, t)
    dv = sc.directions(phi)
    lever = np.array(sc.offset)
    blocked = system.blocks(lever, dv)
    pos, f, left, up = motion.at(t)
    o = pos + lever[0] * f + lever[1] * left + lever[2] * up
    d = dv[:, :1] * f + dv[:, 1:2] * left + dv[:, 2:3] * up
    return o, d, phi, blocked


def pulse_windows(motion: Motion, system: System, sc: Scanner, box_lo: np.ndarray,
                  box_hi: np.ndarray) -> list[tuple[float, float]]:
    """Time intervals in which the scan plane of ``sc`` meets the cut's box within range."""
    n_v, _, _ = sc.plane_basis()
    lever = np.array(sc.offset)
    _, f, left, up = motion.at(motion.t)
    o = motion.pos + lever[0] * f + lever[1] * left + lever[2] * up
    n = n_v[0] * f + n_v[1] * left + n_v[2] * up
    corners = np.array([[x, y, z] for x in (box_lo[0], box_hi[0]) for y in (box_lo[1], box_hi[1])
                        for z in (box_lo[2], box_hi[2])])
    side = np.einsum("mkj,mj->mk", corners[None, :, :] - o[:, None, :], n)
    cuts = (side.min(axis=1) <= 0) & (side.max(axis=1) >= 0)
    gap = np.maximum(np.maximum(box_lo - o, o - box_hi), 0.0)
    cuts &= np.linalg.norm(gap, axis=1) <= system.max_range
    # the edges of each run get one sample of slack; passes never join
    grow = cuts.copy()
    grow[1:] |= cuts[:-1]
    grow[:-1] |= cuts[1:]
    same = np.concatenate([[False], motion.pass_id[1:] == motion.pass_id[:-1]])
    windows = []
    edges = np.flatnonzero(np.diff(np.concatenate([[0], grow.astype(int), [0]])))
    for a, b in zip(edges[::2], edges[1::2], strict=True):
        b = b - 1
        # split a run where the pass changes
        split = [a] + [j for j in range(a + 1, b + 1) if not same[j]] + [b + 1]
        for s0, s1 in zip(split[:-1], split[1:], strict=True):
            if s1 - 1 > s0:
                windows.append((float(motion.t[s0]), float(motion.t[s1 - 1])))
    return windows


def plane_arcs(motion: Motion, sc: Scanner, t: np.ndarray, box_lo: np.ndarray,
               box_hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mirror angles that can reach the cut's box at times t: arc centre and half width.

    The scan plane cuts the box in a convex polygon; seen from a scanner outside the box, its
    corners span an arc below pi, which holds every beam that can enter. Half width above pi
    (every angle) where the scanner is inside the box.
    """
    n_v, u_v, w_v = sc.plane_basis()
    pos, f, left, up = motion.at(t)

    def world(v: np.ndarray) -> np.ndarray:
        return v[0] * f + v[1] * left + v[2] * up

    o = pos + world(np.array(sc.offset))
    n, u, w = world(n_v), world(u_v), world(w_v)
    corners = np.array([[x, y, z] for x in (box_lo[0], box_hi[0])
                        for y in (box_lo[1], box_hi[1]) for z in (box_lo[2], box_hi[2])])
    edges = [(a, b) for a in range(8) for b in range(a + 1, 8)
             if np.count_nonzero(corners[a] != corners[b]) == 1]
    side = np.einsum("mkj,mj->mk", corners[None, :, :] - o[:, None, :], n)  # (m, 8)
    angles, valid = [], []
    for a, b in edges:
        sa, sb = side[:, a], side[:, b]
        with np.errstate(divide="ignore", invalid="ignore"):
            frac = np.clip(np.nan_to_num(sa / (sa - sb)), 0.0, 1.0)
        x = corners[a] + frac[:, None] * (corners[b] - corners[a]) - o
        angles.append(np.arctan2(np.sum(x * u, axis=1), np.sum(x * w, axis=1)))
        valid.append(sa * sb <= 0)
    ang, ok = np.column_stack(angles), np.column_stack(valid)
    c = np.arctan2(np.where(ok, np.sin(ang), 0).sum(axis=1), np.where(ok, np.cos(ang), 0).sum(1))
    rel = np.where(ok, np.mod(ang - c[:, None] + np.pi, 2 * np.pi) - np.pi, 0.0)
    lo, hi = rel.min(axis=1), rel.max(axis=1)
    half = 0.5 * (hi - lo)
    inside = np.all((o >= box_lo) & (o <= box_hi), axis=1)
    half = np.where(inside, np.pi + 1.0, half)
    return c + 0.5 * (lo + hi), half


def pulse_times(motion: Motion, sc: Scanner, windows: list[tuple[float, float]],
                box_lo: np.ndarray, box_hi: np.ndarray, slack: float = np.deg2rad(3.0)
                ) -> Iterator[np.ndarray]:
    """Times (s) of the pulses of ``sc`` in the windows that point into the cut's box, in
    batches of at most CHUNK.

    Pulses lie on the fixed grid k / pulse rate. Per mirror revolution, only the pulses within
    the arc toward the box (:func:`plane_arcs`, the union of the arcs at the revolution's start
    and end, plus ``slack``) are generated, so a short strip costs little.
    """
    rate, scan = sc.pulse_hz, sc.scan_hz
    for ta, tb in windows:
        revs = np.arange(np.floor(ta * scan), np.ceil(tb * scan) + 1)
        t0, t1 = revs / scan, (revs + 1) / scan
        c0, h0 = plane_arcs(motion, sc, np.clip(t0, ta, tb), box_lo, box_hi)
        c1, h1 = plane_arcs(motion, sc, np.clip(t1, ta, tb), box_lo, box_hi)
        rel = np.mod(c1 - c0 + np.pi, 2 * np.pi) - np.pi
        lo, hi = np.minimum(-h0, rel - h1), np.maximum(h0, rel + h1)
        centre, half = c0 + 0.5 * (lo + hi), 0.5 * (hi - lo) + slack
        full = half >= np.pi
        first = centre - sc.spin * half  # the arc's edge the mirror reaches first
        tau = np.mod(sc.spin * (first - sc.phase) / (2 * np.pi), 1.0) / scan
        a = np.where(full, t0, t0 + tau)
        b = np.where(full, t1, a + 2 * half / (2 * np.pi) / scan)
        k0 = np.ceil(np.maximum(a, ta) * rate).astype(np.int64)
        k1 = np.floor(np.minimum(b, tb) * rate).astype(np.int64)
        # consecutive arcs may overlap across a revolution's end: fire each pulse once
        k0 = np.maximum(k0, np.concatenate([[k0[0]], np.maximum.accumulate(k1)[:-1] + 1]))
        count = np.maximum(k1 - k0 + 1, 0)
        if not count.sum():
            continue
        starts = np.repeat(k0 - np.concatenate([[0], np.cumsum(count)[:-1]]), count)
        k = np.arange(int(count.sum()), dtype=np.int64) + starts
        for s0 in range(0, len(k), CHUNK):
            yield k[s0:s0 + CHUNK] / rate


# --------------------------------------------------------------------------- casting


@dataclass
class Hits:
    """First returns of a batch of rays: range (inf: none), material, |cos incidence|."""

    t: np.ndarray
    mat: np.ndarray
    cos: np.ndarray

    @classmethod
    def empty(cls, n: int) -> Hits:
        return cls(np.full(n, np.inf), np.zeros(n, dtype=np.int8), np.ones(n, dtype=np.float32))

    def take(self, idx: np.ndarray | slice, t: np.ndarray, normal: np.ndarray | None,
             d: np.ndarray, mat: int | np.ndarray) -> None:
        """Keep the hits (t at rows idx) that come before what the rays hit so far."""
        closer = t < self.t[idx]
        rows = np.arange(len(self.t))[idx][closer]
        self.t[rows] = t[closer]
        self.mat[rows] = mat if np.isscalar(mat) else np.asarray(mat)[closer]
        if normal is not None:
            nrm = normal if normal.ndim == 1 else normal[closer]
            self.cos[rows] = np.abs(np.sum(nrm * d[closer], axis=1))


def segment_bounds(o: np.ndarray, d: np.ndarray, t_end: np.ndarray) -> np.ndarray:
    """(n, 4) x min, x max, y min, y max of each ray's segment from the origin to t_end."""
    e = o[:, :2] + t_end[:, None] * d[:, :2]
    return np.column_stack([np.minimum(o[:, 0], e[:, 0]), np.maximum(o[:, 0], e[:, 0]),
                            np.minimum(o[:, 1], e[:, 1]), np.maximum(o[:, 1], e[:, 1])])


def _near(bounds: np.ndarray, x0: float, x1: float, y0: float, y1: float) -> np.ndarray:
    return np.flatnonzero((bounds[:, 1] >= x0) & (bounds[:, 0] <= x1)
                          & (bounds[:, 3] >= y0) & (bounds[:, 2] <= y1))


def cast_static(o: np.ndarray, d: np.ndarray, street: Street, bounds: np.ndarray,
                rng: np.random.Generator) -> Hits:
    """First return of each ray on the street (no range limits applied).

    ``bounds`` (n, 4): each ray's reach in x and y (see :func:`segment_bounds`); objects
    outside a ray's reach are not tested against it. Foliage is entered: the beam returns an
    exponentially distributed depth inside the crown (its mean per clump) or passes through.
    """
    n = len(o)
    hits = Hits.empty(n)
    hw = street.half_width
    all_rows = slice(None)
    t, nrm = rc.hit_road(o, d, hw, street.crown, street.grade)
    hits.take(all_rows, t, nrm, d, ASPHALT)
    _cast_sidewalks_and_curbs(o, d, street, hits)
    for fac in street.facades:
        _cast_facade(o, d, street, fac, hits)
    reach = (bounds[:, 0].min(initial=np.inf), bounds[:, 1].max(initial=-np.inf),
             bounds[:, 2].min(initial=np.inf), bounds[:, 3].max(initial=-np.inf))
    for cx, cy, r, lift in street.manholes:
        if not _overlaps(reach, cx - r, cx + r, cy - r, cy + r):
            continue
        idx = _near(bounds, cx - r, cx + r, cy - r, cy + r)
        if len(idx):
            ztop = float(street.road_z(np.array([cx]), np.array([cy]))[0]) + lift
            t, nrm = rc.hit_vertical_cylinder(o[idx], d[idx], cx, cy, r, ztop - 0.1, ztop)
            hits.take(idx, t, nrm, d[idx], LID)
    for box, mat in zip(street.boxes, street.box_mat, strict=True):
        if not _overlaps(reach, box[0], box[3], box[1], box[4]):
            continue
        idx = _near(bounds, box[0], box[3], box[1], box[4])
        if len(idx):
            t, nrm = rc.hit_box(o[idx], d[idx], box[:3], box[3:])
            hits.take(idx, t, nrm, d[idx], int(mat))
    for (cx, cy, r, z0, z1), mat in zip(street.cylinders, street.cyl_mat, strict=True):
        if not _overlaps(reach, cx - r, cx + r, cy - r, cy + r):
            continue
        idx = _near(bounds, cx - r, cx + r, cy - r, cy + r)
        if len(idx):
            t, nrm = rc.hit_vertical_cylinder(o[idx], d[idx], cx, cy, r, z0, z1, cap=False)
            hits.take(idx, t, nrm, d[idx], int(mat))
    for clump in street.foliage:
        c, semi, depth = clump[:3], clump[3:6], clump[6]
        if not _overlaps(reach, c[0] - semi[0], c[0] + semi[0], c[1] - semi[1], c[1] + semi[1]):
            continue
        idx = _near(bounds, c[0] - semi[0], c[0] + semi[0], c[1] - semi[1], c[1] + semi[1])
        if not len(idx):
            continue
        t_in, t_out = rc.hit_ellipsoid(o[idx], d[idx], c, semi)
        inside = np.isfinite(t_in)
        depth_drawn = np.full(len(idx), np.inf)
        depth_drawn[inside] = rng.exponential(depth, int(inside.sum()))
        t = np.where(t_in + depth_drawn < t_out, t_in + depth_drawn, np.inf)
        p = o[idx] + np.where(np.isfinite(t), t, 0.0)[:, None] * d[idx]
        hits.take(idx, t, rc.ellipsoid_normal(p, c, semi), d[idx], FOLIAGE)
    return hits


def _overlaps(reach: tuple[float, float, float, float], x0: float, x1: float, y0: float,
              y1: float) -> bool:
    return reach[1] >= x0 and reach[0] <= x1 and reach[3] >= y0 and reach[2] <= y1


def _cast_sidewalks_and_curbs(o: np.ndarray, d: np.ndarray, street: Street, hits: Hits) -> None:
    hw, g = street.half_width, street.grade
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (street.sidewalk_z(o[:, 0]) - o[:, 2]) / (d[:, 2] - g * d[:, 0])
    t = np.where(t > rc.EPS, t, np.inf)
    y = o[:, 1] + np.where(np.isfinite(t), t, 0.0) * d[:, 1]
    t = np.where(np.abs(y) > hw, t, np.inf)
    hits.take(slice(None), t, np.array([-g, 0.0, 1.0]) / np.hypot(g, 1.0), d, CONCRETE)
    if street.curb <= 0:
        return
    for side in (-1.0, 1.0):
        t = rc.plane_t(o, d, 1, side * hw)
        tt = np.where(np.isfinite(t), t, 0.0)
        x = o[:, 0] + tt * d[:, 0]
        z = o[:, 2] + tt * d[:, 2]
        top = street.sidewalk_z(x)
        t = np.where((z >= top - street.curb) & (z <= top), t, np.inf)
        hits.take(slice(None), t, np.array([0.0, -side, 0.0]), d, CONCRETE)


def facade_cells(street: Street, fac: Facade, x: np.ndarray, z: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For points (x, z) on the facade plane: on a wall (bool), on glass (bool), segment index."""
    seg = np.searchsorted(fac.segments[:, 0], x, side="right") - 1
    segc = np.clip(seg, 0, len(fac.segments) - 1)
    xa, xb, height, curtain = fac.segments[segc].T
    base = street.sidewalk_z(x)
    zz = z - base
    on = (seg >= 0) & (x <= xb) & (zz >= -0.3) & (zz <= height)
    floor = np.floor(zz / fac.floor_height)
    zf = zz - floor * fac.floor_height
    col = np.mod(x - xa - fac.x_phase, fac.spacing)
    punched = ((zf >= fac.sill) & (zf <= fac.sill + fac.win_height) & (col <= fac.width)
               & (x >= xa + 0.5) & (x <= xb - 0.5) & (zz <= height - 0.3))
    wall_of_glass = (curtain > 0) & (zz >= 0.5) & (zz <= height - 0.5)
    return on, on & (punched | wall_of_glass), segc


def room_boxes(street: Street, fac: Facade, x: np.ndarray, z: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    """The rooms behind the windows at points (x, z) of the facade: lo, hi corners (n, 3).

    A punched window opens into a room one window spacing wide; a curtain wall into a hall as
    long as its segment. Rooms are one storey high and ``room_depth`` deep.
    """
    _, _, seg = facade_cells(street, fac, x, z)
    xa, xb, _, curtain = fac.segments[seg].T
    base = street.sidewalk_z(x)
    z0 = base + np.floor((z - base) / fac.floor_height) * fac.floor_height
    col = np.mod(x - xa - fac.x_phase, fac.spacing)
    x0 = np.where(curtain > 0, xa, x - col - (fac.spacing - fac.width) / 2)
    x1 = np.where(curtain > 0, xb, x0 + fac.spacing)
    y0, y1 = sorted((fac.side * fac.y, fac.side * (fac.y + fac.room_depth)))
    lo = np.column_stack([x0, np.full_like(x, y0), z0])
    hi = np.column_stack([x1, np.full_like(x, y1), z0 + fac.floor_height])
    return lo, hi


def _cast_facade(o: np.ndarray, d: np.ndarray, street: Street, fac: Facade, hits: Hits) -> None:
    t = rc.plane_t(o, d, 1, fac.side * fac.y)
    tt = np.where(np.isfinite(t), t, 0.0)
    x = o[:, 0] + tt * d[:, 0]
    z = o[:, 2] + tt * d[:, 2]
    on, glass, _ = facade_cells(street, fac, x, z)
    t = np.where(on, t, np.inf)
    mat = np.where(glass, GLASS, WALL).astype(np.int8)
    hits.take(slice(None), t, np.array([0.0, -float(fac.side), 0.0]), d, mat)


# --------------------------------------------------------------------------- the survey


def point_fractions(system: System, street: Street, plan: DrivePlan, scale: float,
                    rng: np.random.Generator, ahead: np.ndarray | None = None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Shares of each scanner's pulses that return from the cut, driving and standing, and
    how far ahead of the reference point (m, along the drive) each scanner's returns lie.

    Driving: one revolution (512 pulses) per scanner is cast from nine places along the strip
    (plan.strip x scale: the street the cut will hold) in each pass's lane and direction, the
    vehicle standing ``ahead`` (per scanner, from an earlier call) behind each place so the
    scanner's returns fall on it; a return counts when it lies within the cut's width and range
    (the drive sweeps it along the whole strip). Standing: one revolution from each stop's pose
    (see :func:`build_motion`); a return counts only inside the cut. Returns (scanners,),
    (scanners, stops) and (scanners,).
    """
    n_sc = len(system.scanners)
    ahead = np.zeros(n_sc) if ahead is None else ahead
    moving = np.zeros(n_sc)
    standing = np.zeros((n_sc, len(plan.stops)))
    reach, weight = np.zeros(n_sc), np.zeros(n_sc)
    strip = plan.strip * scale
    places = [(p, x, -1) for p in plan.passes for x in np.linspace(0.05, 0.95, 9) * strip]
    places += [(plan.passes[s.pass_index], s.fraction * strip, j)
               for j, s in enumerate(plan.stops)]
    n_moving = 9 * len(plan.passes)
    # one cast for all revolutions: the street's objects are looped over once
    stands = [(p, x - p.direction * (plan.footprint if stop >= 0 else ahead[i]), stop, i)
              for p, x, stop in places for i in range(n_sc)]
    rays = [(p, x, stop, i, *_one_revolution(system, street, system.scanners[i], x, p.lane,
                                             p.direction)) for p, x, stop, i in stands]
    o = np.concatenate([r[4] for r in rays])
    d = np.concatenate([r[5] for r in rays])
    hits = cast_static(o, d, street, segment_bounds(o, d, np.full(len(o), 80.0)), rng)
    q_all = o + np.where(np.isfinite(hits.t), hits.t, 0.0)[:, None] * d
    ok_all = ((hits.t >= system.min_range) & (hits.t <= system.max_range)
              & (q_all[:, 1] >= street.crop_y[0]) & (q_all[:, 1] <= street.crop_y[1]))
    size = len(rays[0][4])
    for j, (p, x, stop, i, _, _, free) in enumerate(rays):
        q = q_all[j * size:(j + 1) * size]
        ok = free & ok_all[j * size:(j + 1) * size]
        if stop >= 0:
            standing[i, stop] = np.mean(ok & (q[:, 0] >= 0) & (q[:, 0] <= strip))
            continue
        moving[i] += ok.mean() / n_moving
        reach[i] += float(np.sum(q[ok, 0] - x) * p.direction)
        weight[i] += int(ok.sum())
    return np.maximum(moving, 1e-3), standing, reach / np.maximum(weight, 1)


def _one_revolution(system: System, street: Street, sc: Scanner, x: float, y: float,
                    direction: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rays of one mirror revolution (512 pulses) from the vehicle standing level at (x, y):
    origins, directions and whether the body leaves the beam free."""
    phi = np.linspace(-np.pi, np.pi, 512, endpoint=False)
    heading = np.array([0.0 if direction > 0 else np.pi])
    ground = np.array([x, y, float(street.road_z(np.array([x]), np.array([y]))[0])])
    f, left, up = vehicle_axes(np.zeros(1), np.zeros(1), heading)
    dv = sc.directions(phi)
    lever = np.array(sc.offset)
    free = ~system.blocks(lever, dv)
    ref = ground + system.reference_height * up[0]
    o = np.tile(ref + lever[0] * f[0] + lever[1] * left[0] + lever[2] * up[0], (len(phi), 1))
    d = np.outer(dv[:, 0], f[0]) + np.outer(dv[:, 1], left[0]) + np.outer(dv[:, 2], up[0])
    return o, d, free


def run_survey(system: System, street: Street, motion: Motion, bodies: list[Mover | Arm],
               strip: float, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Fire every pulse that can reach the cut; keep the first returns inside it.

    Returns arrays over the kept pulses: ``o``, ``d`` (n, 3) origin and direction; ``t`` GPS
    time; ``src`` scanner id; ``phi`` mirror angle (degrees); ``r``, ``mat``, ``cos`` the first
    return on the static street (r = inf when it falls outside the cut or range); ``r_dyn``,
    ``dyn``, ``cos_dyn`` the hit on a moving body in front of it (``dyn`` = index into
    ``bodies``, -1 none); ``sky`` a sparse sample of beams that met nothing at all.
    """
    x_ends = np.array([0.0, strip])
    z = street.road_z(np.concatenate([x_ends, x_ends]), np.array([0, 0, 0, 0.0]))
    box_lo = np.array([0.0, street.crop_y[0], z.min() - street.crown - 0.5])
    box_hi = np.array([strip, street.crop_y[1], z.max() + street.curb + street.top])
    names = ("o", "d", "t", "src", "phi", "r", "mat", "cos", "r_dyn", "dyn", "cos_dyn", "sky")
    cols: dict[str, list[np.ndarray]] = {k: [] for k in names}

    def in_cut(p: np.ndarray) -> np.ndarray:
        return ((p[:, 0] >= 0) & (p[:, 0] <= strip) & (p[:, 1] >= street.crop_y[0])
                & (p[:, 1] <= street.crop_y[1]))

    for sc in system.scanners:
        windows = pulse_windows(motion, system, sc, box_lo, box_hi)
        for t in pulse_times(motion, sc, windows, box_lo, box_hi):
            o, d, phi, blocked = scanner_rays(motion, system, sc, t)
            t_in, t_out, _ = rc.slab(o, d, box_lo, box_hi)
            enter = np.flatnonzero(~blocked & (t_in <= t_out) & (t_out > system.min_range)
                                   & (t_in < system.max_range))
            if not len(enter):
                continue
            o, d, t, phi = o[enter], d[enter], t[enter], phi[enter]
            bounds = segment_bounds(o, d, np.minimum(t_out[enter], system.max_range))
            hits = cast_static(o, d, street, bounds, rng)
            r_dyn, dyn, cos_dyn = cast_dynamic(o, d, t, bodies, bounds)
            in_range = (hits.t >= system.min_range) & (hits.t <= system.max_range)
            r = np.where(in_range, hits.t, np.inf)
            r = np.where(in_cut(o + np.where(np.isfinite(r), r, 0.0)[:, None] * d), r, np.inf)
            ok_dyn = ((r_dyn < hits.t) & (r_dyn >= system.min_range)
                      & (r_dyn <= system.max_range))
            ok_dyn &= in_cut(o + np.where(ok_dyn, r_dyn, 0.0)[:, None] * d)
            sky = ~np.isfinite(hits.t) & ~ok_dyn & (rng.random(len(t)) < SKY_SAMPLE)
            keep = np.flatnonzero(np.isfinite(r) | ok_dyn | sky)
            for key, val in (("o", o), ("d", d), ("t", t), ("r", r), ("mat", hits.mat),
                             ("cos", hits.cos), ("dyn", dyn), ("cos_dyn", cos_dyn),
                             ("sky", sky)):
                cols[key].append(val[keep])
            cols["r_dyn"].append(np.where(ok_dyn, r_dyn, np.inf)[keep])
            cols["phi"].append(np.rad2deg(phi[keep]).astype(np.float32))
            cols["src"].append(np.full(len(keep), sc.source_id, dtype=np.uint16))
    out = {k: np.concatenate(v) if v else np.zeros(0) for k, v in cols.items()}
    out["dyn"] = np.where(np.isfinite(out["r_dyn"]), out["dyn"], -1).astype(np.int16)
    return out
