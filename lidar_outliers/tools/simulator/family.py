"""What differs between real mobile-mapping systems and surveys, drawn from a seed.

A detector tuned to one simulated geometry learns that geometry. Here every fact that differs
between real systems and real surveys is a random draw, bounded by what real systems do
(published specifications, rounded; ranges are inclusive):

==========================  ==============================================================
fact                        range drawn
==========================  ==============================================================
profile scanners            1-3, in one of four layouts: *butterfly* (two planes turned
                            +-30-60 deg from the perpendicular to the drive: Optech LYNX,
                            Riegl VMX-450 / VMX-2HA, Trimble MX9), *perpendicular* (one
                            plane across the drive, tilted 0-25 deg fore/aft: Leica
                            Pegasus:Two, Riegl VMQ-1HA), *butterfly + tilted* (a third plane
                            tilted 20-45 deg, the way spinning Velodyne/Ouster heads are
                            racked on mapping rigs), *perpendicular + oblique*
mounting height             1.8-3.2 m above the road, at least 0.25 m above the roof
lever arms                  on a rack at the back of the roof (from 0.2 m behind to 0.8 m
                            ahead of the rear bumper; a tilted head also at the front),
                            sideways +-0.3-0.8 m (pairs), from the trajectory's reference
                            point (an IMU on the roof, 1.6-2.3 m up)
mirror rate                 50-250 Hz per scanner (lines per second)
pulse rate                  100 kHz - 1 MHz per scanner (before the size conditioning below)
range noise                 2-10 mm (1 sigma, along the beam)
blind zone / max range      1.5-3.0 m / 100-250 m
vehicle                     4.4-6.0 m long, 1.75-2.1 m wide, roof 1.5-2.2 m; the body
                            (lower body and a shorter cabin) blocks the beams that meet it
road                        half width 3.5-9 m, crown 0-12 cm, grade -4..+4 %, texture
                            1-5 mm RMS, raised manhole lids 0.5-3 cm, curbs 8-20 cm (or
                            none), sidewalks 1.5-5 m
street furniture            facades (4-20 m high, gaps for alleys, punched windows or glass
                            curtain walls, rooms 3-8 m deep behind the glass), parked cars,
                            poles with and without signs, trees and hedges (rough clumps the
                            beam enters 5-30 cm), an overpass or a sign gantry (25 %)
drive                       1-3 passes in alternating directions, lanes and gentle curves
                            (+-0.5 m weave, a lane change in 25 % of passes), 0-20 m/s by
                            condition, 0-2 stops of 1-10 s, braking 0.8-2.5 m/s^2
cut                         5-60 m of street; across it the asphalt only, to the facades,
                            or into the buildings, drawn per side
frame                       a projected grid: azimuth 0-360 deg, easting 300-700 km,
                            northing 4000-6000 km, 0-500 m elevation; GPS seconds of week
==========================  ==============================================================

Size conditioning: a condition is one of the paper's clouds, so the survey must give about its
number of points (Table 1, times ``scale``). Points per second on the cut follow from the drawn
scanners (a quick cast of one revolution each); the strip length is then solved for that count,
and where it would leave 5-60 m fewer passes, other speeds and stops, and only then other pulse
rates bring it back (:func:`condition_size`). All draws come from independent streams, so the
scanners' layout and mounting and the street of a seed are the same for every condition and
``scale``; the rate setting and the drive are the condition's.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

#: Kinds of points; code 0 is a real surface point, every other code an outlier. Index = code.
KIND_NAMES: tuple[str, ...] = (
    "surface",
    "exhaust_plume",  # condensation and dust clumps, also at a standstill
    "water_multipath",  # mirror returns below a wet road
    "barrier_arm",  # a barrier arm moving up and down
    "near_surface",  # returns a few cm above the ground
    "isolated",  # single early returns in front of a surface
    "glass_multipath",  # mirror returns behind windows
    "moving_object",  # passing vehicles, cyclists, pedestrians
    "airborne",  # rain, snow, insects, birds
    "mist",  # mist and spray in a band just above the road
)
(SURFACE, EXHAUST, WATER, ARM, NEAR_SURFACE, ISOLATED, GLASS_MP, MOVING, AIRBORNE,
 MIST) = range(len(KIND_NAMES))

#: Table 1 of the paper: total points and outliers per cloud.
TABLE1 = {"A": (1098689, 11035), "B": (295147, 872), "C": (237740, 31)}

# Materials: index into REFLECTIVITY; they shape the intensity and tell the surfaces apart.
(ASPHALT, WET, CONCRETE, WALL, GLASS, INTERIOR, CAR, POLE, SIGN, FOLIAGE, LID, ARM_PAINT,
 MOVER, FOG, BARK) = range(15)
REFLECTIVITY = np.array([0.12, 0.04, 0.35, 0.45, 0.08, 0.4, 0.6, 0.4, 0.9, 0.3, 0.22, 0.85,
                         0.5, 0.08, 0.25])
#: Materials of the ground (texture, puddles, mist and near-surface returns live on them).
GROUND = (ASPHALT, WET, CONCRETE)

LAYOUTS = ("butterfly", "perpendicular", "butterfly+tilted", "perpendicular+oblique")
LAYOUT_P = (0.4, 0.2, 0.25, 0.15)
#: Strip length at scale 1 (m): the size conditioning keeps it in this range.
STRIP_RANGE = (5.0, 60.0)
#: Street built around the strip (m before 0 and after the longest strip).
STREET_MARGIN = 70.0
POSE_HZ = 200.0


@dataclass(frozen=True)
class Scanner:
    """One 2D profile scanner on the vehicle (vehicle frame: x forward, y left, z up).

    ``offset`` is the lever arm from the trajectory's reference point. The scan plane's normal
    points ``yaw_deg`` from the driving direction (0: the plane stands across the drive) and
    ``pitch_deg`` above the horizontal (the plane leans fore or aft). The mirror turns
    ``spin`` (+1/-1) at ``scan_hz``, firing ``pulse_hz``; at t = 0 it points ``phase`` radians
    from the plane's downward direction.
    """

    source_id: int
    offset: tuple[float, float, float]
    yaw_deg: float
    phase: float = 0.0
    scan_hz: float = 150.0
    pulse_hz: float = 100_000.0
    pitch_deg: float = 0.0
    spin: int = 1

    def plane_basis(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Normal n, in-plane horizontal u and in-plane downward w (vehicle frame, unit)."""
        yaw, pitch = np.deg2rad(self.yaw_deg), np.deg2rad(self.pitch_deg)
        n = np.array([np.cos(yaw) * np.cos(pitch), np.sin(yaw) * np.cos(pitch), np.sin(pitch)])
        u = np.array([np.sin(yaw), -np.cos(yaw), 0.0])
        w = np.cross(n, u)
        if w[2] > 0:
            w = -w
        return n, u, w

    def directions(self, phi: np.ndarray) -> np.ndarray:
        """Beam directions (n, 3) in the vehicle frame at mirror angles phi (from downward)."""
        _, u, w = self.plane_basis()
        return np.outer(np.sin(phi), u) + np.outer(np.cos(phi), w)


@dataclass(frozen=True)
class System:
    """A mobile-mapping system: its scanners, their noise and range, and the vehicle."""

    layout: str
    scanners: tuple[Scanner, ...]
    reference_height: float  # trajectory reference point above the road
    range_sigma: float
    min_range: float
    max_range: float
    vehicle_length: float
    vehicle_width: float
    roof_height: float
    tailpipe_left: float  # the exhaust leaves the rear bumper this far left of centre
    intensity_gain: float = 1.0

    def body_boxes(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """The vehicle's body (vehicle frame, relative to the reference point) as lo, hi
        corners of two boxes: the lower body over the whole length, up to 1 m above the road,
        and the cabin up to the roof, shorter at both ends."""
        h, half = self.reference_height, self.vehicle_length / 2
        w = self.vehicle_width / 2
        lower = (np.array([-half, -w, -h + 0.15]), np.array([half, w, 1.0 - h]))
        cabin = (np.array([-0.6 * half, -w + 0.1, 1.0 - h]),
                 np.array([0.7 * half, w - 0.1, self.roof_height - h]))
        return [lower, cabin]

    def blocks(self, origin: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """Whether the body stops beams leaving ``origin`` (vehicle frame) along directions."""
        o = np.broadcast_to(origin, directions.shape)
        out = np.zeros(len(directions), dtype=bool)
        for lo, hi in self.body_boxes():
            t_in, t_out = _box_span(o, directions, lo, hi)
            out |= (t_in <= t_out) & (t_out > 1e-6)
        return out


def _box_span(o: np.ndarray, d: np.ndarray, lo: np.ndarray, hi: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray]:
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (lo - o) / d, (hi - o) / d
    near = np.where(np.isnan(t1), -np.inf, np.fmin(t1, t2)).max(axis=1)
    far = np.where(np.isnan(t1), np.inf, np.fmax(t1, t2)).min(axis=1)
    return near, far


#: The LYNX-like pair the transient detector's default lever arms describe (scan planes
#: vertical, turned +-45 degrees, 150 Hz, 100 kHz, on the roof at the reference point's height).
SCANNERS = (
    Scanner(1, offset=(-0.6, 0.45, 0.0), yaw_deg=45.0, phase=0.0),
    Scanner(2, offset=(-0.6, -0.45, 0.0), yaw_deg=-45.0, phase=1.3),
)


@dataclass(frozen=True, eq=False)
class Facade:
    """Building fronts on one side of the street: a vertical plane at |y| = ``y``.

    ``segments`` (k, 4): x start, x end, height, curtain (1: a glass curtain wall). Punched
    windows sit on a grid: ``spacing`` apart along x, ``width`` x ``height`` each, ``sill``
    above each floor of ``floor_height``; a room ``room_depth`` deep lies behind each.
    """

    side: int  # +1: y > 0 (left of +x), -1: y < 0
    y: float
    segments: np.ndarray
    spacing: float
    width: float
    win_height: float
    sill: float
    floor_height: float
    x_phase: float
    room_depth: float


@dataclass(frozen=True, eq=False)
class Street:
    """The surveyed street in its local frame: x along it, y to the left, z up (road crown y=0).

    Arrays: ``texture`` (k, 4) kx, ky, phase, amplitude; ``manholes`` (m, 4) cx, cy, radius,
    lift; ``boxes`` (b, 6) lo, hi with ``box_mat``; ``cylinders`` (c, 5) cx, cy, radius, z0, z1
    with ``cyl_mat``; ``foliage`` (f, 7) centre, semi-axes, mean penetration depth.
    """

    half_width: float
    crown: float
    grade: float
    roughness: float
    curb: float
    sidewalk: float
    facades: tuple[Facade, ...]
    crop_y: tuple[float, float]
    texture: np.ndarray
    manholes: np.ndarray
    boxes: np.ndarray
    box_mat: np.ndarray
    cylinders: np.ndarray
    cyl_mat: np.ndarray
    foliage: np.ndarray
    top: float  # highest surface above the road (m)

    def road_z(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Height of the asphalt (without texture): z = g x - a y^2."""
        return self.grade * x - self.crown / self.half_width**2 * y**2

    def sidewalk_z(self, x: np.ndarray) -> np.ndarray:
        return self.grade * x - self.crown + self.curb

    def ground_z(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Bare ground (road inside the curbs, sidewalk outside) under (x, y)."""
        return np.where(np.abs(y) <= self.half_width, self.road_z(x, y), self.sidewalk_z(x))


@dataclass(frozen=True)
class Stop:
    pass_index: int
    fraction: float  # where along the strip the scan planes meet the ground (0-1)
    seconds: float  # at scale 1
    decel: float  # m/s^2 at scale 1


@dataclass(frozen=True)
class PassPlan:
    direction: int  # +1 along +x, -1 along -x
    lane: float  # y of the reference point
    speed: float  # cruise, m/s
    weave: tuple[float, float, float]  # amplitude m, wavelength m, phase
    lane_change: tuple[float, float, float]  # shift m (0: none), centre fraction, length m


@dataclass(frozen=True)
class DrivePlan:
    passes: tuple[PassPlan, ...]
    stops: tuple[Stop, ...]
    gaps: tuple[float, ...]  # seconds between passes (the vehicle turns, not scanning)
    start: float  # GPS seconds of week of the first pass
    strip: float  # strip length at scale 1 (m)
    footprint: float = 0.0  # the scan planes' returns lie this far ahead of the reference (m)


@dataclass(frozen=True)
class Frame:
    """Local street frame -> projected world coordinates: rotate by azimuth, then shift."""

    azimuth: float  # radians, counter-clockwise from east
    origin: tuple[float, float, float]

    def to_world(self, xyz: np.ndarray) -> np.ndarray:
        c, s = np.cos(self.azimuth), np.sin(self.azimuth)
        out = np.empty_like(xyz)
        out[:, 0] = c * xyz[:, 0] - s * xyz[:, 1] + self.origin[0]
        out[:, 1] = s * xyz[:, 0] + c * xyz[:, 1] + self.origin[1]
        out[:, 2] = xyz[:, 2] + self.origin[2]
        return out

    def to_local(self, xyz: np.ndarray) -> np.ndarray:
        c, s = np.cos(self.azimuth), np.sin(self.azimuth)
        x = xyz[:, 0] - self.origin[0]
        y = xyz[:, 1] - self.origin[1]
        out = np.empty_like(xyz, dtype=np.float64)
        out[:, 0] = c * x + s * y
        out[:, 1] = -s * x + c * y
        out[:, 2] = xyz[:, 2] - self.origin[2]
        return out


# --------------------------------------------------------------------------- conditions


@dataclass(frozen=True)
class Condition:
    """One of the paper's three days (Table 1) as a preset: the outlier share and character.

    ``kinds`` maps outlier codes to the range their weight in the mix is drawn from; kinds in
    ``optional`` appear only where the drawn street allows (glass needs windows in the cut).
    """

    name: str
    share: float
    points: int
    passes: tuple[int, int]
    speed: tuple[float, float]  # cruise speed, m/s (log-uniform)
    stops: tuple[int, int]
    wet: bool
    cold: bool
    kinds: dict[int, tuple[float, float]] = field(default_factory=dict)
    optional: frozenset[int] = frozenset()


# --------------------------------------------------------------------------- the draws


def stream(seed: int, *key: int) -> np.random.Generator:
    """An independent random stream for one part of the draw (system, street, drive, ...)."""
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=key))


def draw_system(rng: np.random.Generator) -> System:
    """Scanners, their mounting, rates and noise, and the vehicle (ranges: module docstring)."""
    layout = str(rng.choice(LAYOUTS, p=LAYOUT_P))
    roof = rng.uniform(1.5, 2.2)
    ref_h = roof + 0.1  # IMU on the roof rack
    length, width = rng.uniform(4.4, 6.0), rng.uniform(1.75, 2.1)
    shared_scan = rng.uniform(50.0, 250.0)
    shared_pulse = float(np.exp(rng.uniform(np.log(1e5), np.log(1e6))))
    same_rates = rng.random() < 0.7

    def rates() -> tuple[float, float]:
        if same_rates:
            return shared_scan, shared_pulse
        return rng.uniform(50.0, 250.0), float(np.exp(rng.uniform(np.log(1e5), np.log(1e6))))

    def up() -> float:
        return rng.uniform(max(1.8, roof + 0.25), 3.2) - ref_h

    def rear() -> float:  # on a rack at the back of the roof, over the rear bumper
        return rng.uniform(-length / 2 - 0.2, -length / 2 + 0.8)

    specs: list[tuple[tuple[float, float, float], float, float]] = []  # offset, yaw, pitch
    if layout.startswith("butterfly"):
        yaw = rng.uniform(30.0, 60.0)
        toe = 1.0 if rng.random() < 0.5 else -1.0  # planes opening forward or backward
        fwd, side, z = rear(), rng.uniform(0.3, 0.8), up()
        pitch = rng.uniform(-10.0, 10.0)
        for s in (1.0, -1.0):
            specs.append(((fwd, s * side, z), s * toe * yaw + rng.normal(0, 1.5), pitch))
        if layout == "butterfly+tilted":
            tilt = rng.uniform(20.0, 45.0) * (1.0 if rng.random() < 0.5 else -1.0)
            # the tilted head sits on the rack or looks ahead from the front of the roof
            fwd3 = rear() if rng.random() < 0.6 else rng.uniform(length / 2 - 0.8, length / 2)
            specs.append(((fwd3, rng.uniform(-0.2, 0.2), up()), rng.uniform(-5.0, 5.0), tilt))
    else:
        specs.append(((rear(), rng.uniform(-0.2, 0.2), up()),
                      rng.uniform(-5.0, 5.0), rng.uniform(-25.0, 25.0)))
        if layout == "perpendicular+oblique":
            s = 1.0 if rng.random() < 0.5 else -1.0
            specs.append(((rear(), s * rng.uniform(0.3, 0.8), up()),
                          s * rng.uniform(30.0, 60.0), rng.uniform(-10.0, 10.0)))
    scanners = []
    for i, (offset, yaw, pitch) in enumerate(specs):
        scan_hz, pulse_hz = rates()
        scanners.append(Scanner(
            source_id=i + 1, offset=tuple(float(v) for v in offset), yaw_deg=float(yaw),
            phase=float(rng.uniform(0, 2 * np.pi)), scan_hz=float(scan_hz),
            pulse_hz=float(pulse_hz), pitch_deg=float(pitch),
            spin=1 if rng.random() < 0.5 else -1,
        ))
    return System(
        layout=layout, scanners=tuple(scanners), reference_height=float(ref_h),
        range_sigma=float(rng.uniform(0.002, 0.010)), min_range=float(rng.uniform(1.5, 3.0)),
        max_range=float(rng.uniform(100.0, 250.0)), vehicle_length=float(length),
        vehicle_width=float(width), roof_height=float(roof),
        tailpipe_left=float(rng.choice([-1.0, 1.0]) * rng.uniform(0.3, 0.6)),
        intensity_gain=float(rng.uniform(0.7, 1.3)),
    )


def draw_street(rng: np.random.Generator) -> Street:
    """The street around the strip: x from -STREET_MARGIN to 60 + STREET_MARGIN m."""
    x0, x1 = -STREET_MARGIN, STRIP_RANGE[1] + STREET_MARGIN
    hw = rng.uniform(3.5, 9.0)
    crown = rng.uniform(0.0, min(0.12, 0.025 * hw))  # cross slope at the edges <= 5 %
    grade = rng.uniform(-0.04, 0.04)
    roughness = rng.uniform(0.001, 0.005)
    curb = rng.uniform(0.08, 0.2) if rng.random() < 0.85 else 0.0
    sidewalk = rng.uniform(1.5, 5.0)
    street = Street(hw, crown, grade, roughness, curb, sidewalk, (), (0.0, 0.0),
                    np.zeros((0, 4)), np.zeros((0, 4)), np.zeros((0, 6)), np.zeros(0, int),
                    np.zeros((0, 5)), np.zeros(0, int), np.zeros((0, 7)), 6.0)

    facades = []
    for side in (1, -1):
        if rng.random() < 0.8:
            facades.append(_draw_facade(rng, side, hw + sidewalk, x0, x1))
    boxes: list[list[float]] = []
    box_mat: list[int] = []
    cyls: list[list[float]] = []
    cyl_mat: list[int] = []
    foliage: list[list[float]] = []

    # parked cars: a body and a narrower cabin, along the curb on either side
    for side in (1, -1):
        if rng.random() < 0.25:
            continue
        x = x0 + rng.uniform(0, 6)
        while x < x1:
            clen = rng.uniform(3.8, 5.2)
            if rng.random() < 0.7:
                cw, ch = rng.uniform(1.7, 2.0), rng.uniform(1.4, 1.9)
                yc = side * (hw - rng.uniform(0.2, 0.4) - cw / 2)
                z = float(street.road_z(np.array([x + clen / 2]), np.array([yc]))[0])
                boxes.append([x, yc - cw / 2, z + 0.25, x + clen, yc + cw / 2, z + 0.95])
                box_mat.append(CAR)
                boxes.append([x + 0.2 * clen, yc - cw / 2 + 0.1, z + 0.95, x + 0.8 * clen,
                              yc + cw / 2 - 0.1, z + ch])
                box_mat.append(CAR)
            x += clen + rng.uniform(0.5, 3.0)

    # poles (some with a sign panel), trees and hedges on the sidewalks
    for side in (1, -1):
        y_pole = side * (hw + rng.uniform(0.4, 1.0))
        x = x0 + rng.uniform(0, 20)
        while x < x1:
            zb = float(street.sidewalk_z(np.array([x]))[0])
            height = rng.uniform(4.0, 10.0)
            cyls.append([x, y_pole, rng.uniform(0.05, 0.15), zb, zb + height])
            cyl_mat.append(POLE)
            if rng.random() < 0.35:
                pw, ph = rng.uniform(0.5, 1.5), rng.uniform(0.5, 1.2)
                zt = zb + rng.uniform(2.2, height - 0.2)
                boxes.append([x - 0.03, y_pole - pw / 2, zt - ph, x + 0.03, y_pole + pw / 2, zt])
                box_mat.append(SIGN)
            x += rng.uniform(15.0, 40.0)
        if rng.random() < 0.6:
            y_tree = side * (hw + rng.uniform(0.8, max(0.9, sidewalk - 0.8)))
            x = x0 + rng.uniform(0, 15)
            while x < x1:
                zb = float(street.sidewalk_z(np.array([x]))[0])
                trunk = rng.uniform(2.0, 4.0)
                cyls.append([x, y_tree, rng.uniform(0.1, 0.3), zb, zb + trunk + 0.5])
                cyl_mat.append(BARK)
                semi = [rng.uniform(1.2, 3.0), rng.uniform(1.2, 3.0), rng.uniform(1.2, 3.0)]
                foliage.append([x, y_tree, zb + trunk + semi[2], *semi,
                                rng.uniform(0.05, 0.3)])
                x += rng.uniform(8.0, 20.0)
        if rng.random() < 0.4:
            y_hedge = side * (hw + sidewalk - rng.uniform(0.4, 1.0))
            x = x0 + rng.uniform(0, 10)
            while x < x1:
                zb = float(street.sidewalk_z(np.array([x]))[0])
                semi = [rng.uniform(0.6, 2.5), rng.uniform(0.3, 0.6), rng.uniform(0.4, 0.9)]
                foliage.append([x, y_hedge, zb + 0.6 * semi[2], *semi, rng.uniform(0.05, 0.2)])
                x += rng.uniform(4.0, 15.0)

    # an overpass or a sign gantry across the street
    if rng.random() < 0.25:
        xo = rng.uniform(0.0, STRIP_RANGE[1])
        z = float(street.road_z(np.array([xo]), np.array([0.0]))[0])
        clearance = rng.uniform(4.6, 6.5)
        if rng.random() < 0.5:  # overpass deck
            depth, thick = rng.uniform(8.0, 15.0), rng.uniform(0.8, 1.5)
        else:  # gantry: a sign panel on a beam
            depth, thick = rng.uniform(0.3, 0.6), rng.uniform(1.5, 2.5)
        span = hw + sidewalk + 2.0
        boxes.append([xo, -span, z + clearance, xo + depth, span, z + clearance + thick])
        box_mat.append(CONCRETE if depth > 1 else SIGN)

    manholes = []
    for x in np.arange(x0 + rng.uniform(0, 10), x1, 10.0):
        if rng.random() < 0.5:
            manholes.append([x + rng.uniform(-3, 3), rng.uniform(-0.8, 0.8) * hw,
                             rng.uniform(0.3, 0.4), rng.uniform(0.005, 0.03)])

    # asphalt texture: sinusoids of 3-40 cm wavelength summing to the roughness RMS
    k = 12
    wl = rng.uniform(0.03, 0.4, k)
    ang = rng.uniform(0, np.pi, k)
    texture = np.column_stack([2 * np.pi / wl * np.cos(ang), 2 * np.pi / wl * np.sin(ang),
                               rng.uniform(0, 2 * np.pi, k),
                               np.full(k, roughness * np.sqrt(2 / k))])

    crop = []
    for side in (1, -1):
        facade = [f for f in facades if f.side == side]
        mode = rng.choice(["asphalt", "facade", "inside"], p=[0.3, 0.3, 0.4])
        if mode == "asphalt" or not facade:
            edge = hw * rng.uniform(0.6, 1.0) if mode == "asphalt" else hw + sidewalk * 0.9
        elif mode == "facade":
            edge = facade[0].y - 0.05
        else:
            edge = facade[0].y + facade[0].room_depth + 0.5
        crop.append(float(edge))
    tops = [f.segments[:, 2].max() for f in facades if len(f.segments)]
    top = max([6.0, *tops, *(np.array(cyls)[:, 4] - street.sidewalk_z(np.array(cyls)[:, 0])
                             if cyls else [])])
    return replace(
        street, facades=tuple(facades), crop_y=(-crop[1], crop[0]), texture=texture,
        manholes=np.array(manholes, dtype=float).reshape(-1, 4),
        boxes=np.array(boxes, dtype=float).reshape(-1, 6), box_mat=np.array(box_mat, int),
        cylinders=np.array(cyls, dtype=float).reshape(-1, 5), cyl_mat=np.array(cyl_mat, int),
        foliage=np.array(foliage, dtype=float).reshape(-1, 7), top=float(top) + 1.0,
    )


def _draw_facade(rng: np.random.Generator, side: int, y: float, x0: float, x1: float) -> Facade:
    segments = []
    x = x0
    while x < x1:
        length = rng.uniform(10.0, 60.0)
        segments.append([x, x + length, rng.uniform(4.0, 20.0), float(rng.random() < 0.15)])
        x += length + (rng.uniform(3.0, 10.0) if rng.random() < 0.3 else 0.0)
    floor_h = rng.uniform(3.0, 3.6)
    win_h = rng.uniform(1.0, min(2.2, floor_h - 0.9))
    spacing = rng.uniform(2.5, 5.0)
    return Facade(
        side=side, y=float(y), segments=np.array(segments), spacing=float(spacing),
        width=float(rng.uniform(0.8, spacing - 0.6)), win_height=float(win_h),
        sill=float(rng.uniform(0.5, floor_h - win_h - 0.2)), floor_height=float(floor_h),
        x_phase=float(rng.uniform(0, spacing)), room_depth=float(rng.uniform(3.0, 8.0)),
    )


def draw_drive(rng: np.random.Generator, cond: Condition, street: Street) -> DrivePlan:
    """Passes, lanes, speeds and stops (before the size conditioning)."""
    n_pass = int(rng.integers(cond.passes[0], cond.passes[1] + 1))
    direction = 1 if rng.random() < 0.5 else -1
    lo, hi = np.log(cond.speed[0]), np.log(cond.speed[1])
    cruise = float(np.exp(rng.uniform(lo, hi)))
    lane_max = street.half_width - 1.4
    passes = []
    for _ in range(n_pass):
        keep_right = rng.random() < 0.8
        side = -direction if keep_right else direction
        lane = side * rng.uniform(0.2, lane_max) if lane_max > 0.2 else 0.0
        weave = (float(rng.uniform(0, 0.5)), float(rng.uniform(40.0, 150.0)),
                 float(rng.uniform(0, 2 * np.pi)))
        change = (0.0, 0.5, 30.0)
        if rng.random() < 0.25:
            target = float(np.clip(-lane + rng.normal(0, 0.5), -lane_max, lane_max))
            change = (target - lane, float(rng.uniform(0.2, 0.8)), float(rng.uniform(15.0, 40.0)))
        speed = float(np.clip(cruise * rng.uniform(0.85, 1.15), 0.5, 20.0))
        passes.append(PassPlan(direction, float(lane), speed, weave, change))
        direction = -direction
    n_stops = int(rng.integers(cond.stops[0], cond.stops[1] + 1))
    stop_passes = sorted(rng.choice(n_pass, size=min(n_stops, n_pass), replace=False).tolist())
    stops = tuple(Stop(int(p), float(rng.uniform(0.25, 0.75)), float(rng.uniform(1.0, 10.0)),
                       float(rng.uniform(0.8, 2.5))) for p in stop_passes)
    gaps = tuple(float(rng.uniform(15.0, 60.0)) for _ in range(n_pass - 1))
    return DrivePlan(tuple(passes), stops, gaps, float(rng.uniform(1e4, 5.9e5)),
                     float(np.exp(rng.uniform(np.log(STRIP_RANGE[0]), np.log(STRIP_RANGE[1])))))


def draw_frame(rng: np.random.Generator) -> Frame:
    """A projected frame: the street's azimuth and where its origin lies (easting, northing,
    elevation), so coordinates look like a real delivery's and no axis follows the street."""
    east, north, up = rng.uniform(3e5, 7e5), rng.uniform(4e6, 6e6), rng.uniform(0, 500)
    return Frame(float(rng.uniform(0, 2 * np.pi)),
                 (round(float(east), 3), round(float(north), 3), round(float(up), 3)))


def moving_seconds(drive: DrivePlan, length: float) -> float:
    """Seconds the vehicle moves over a strip of ``length`` m on all passes (scale 1).

    Cruising takes length / speed per pass; braking over the last d metres before a stop
    (d = min(v^2 / 2a, the strip before the stop)) adds sqrt(2 d / a) - d / v, and pulling
    away the same.
    """
    total = sum(length / p.speed for p in drive.passes)
    for s in drive.stops:
        p = drive.passes[s.pass_index]
        before = s.fraction if p.direction > 0 else 1.0 - s.fraction
        reach = p.speed**2 / (2 * s.decel)
        for d in (min(reach, before * length), min(reach, (1 - before) * length)):
            total += np.sqrt(2 * d / s.decel) - d / p.speed
    return float(total)


def condition_size(system: System, drive: DrivePlan, moving: np.ndarray, standing: np.ndarray,
                   cond: Condition) -> tuple[System, DrivePlan]:
    """Set the strip so the survey gives the condition's number of points at scale 1.

    ``moving`` (one per scanner): the share of its pulses that return from the cut while the
    vehicle drives over it; ``standing`` (scanners x stops): the share while it stands at each
    stop. Points = sum over scanners of pulse rate x (moving share x :func:`moving_seconds` +
    standing share x wait). The strip length solving that is kept when it lies in STRIP_RANGE.
    Otherwise, each step only while the strip is still out of range and toward the drawn
    strip length: passes without a stop are left out (too many points); speeds and waits are
    scaled by one factor within the condition's speeds; the pulse rates by one factor within
    100 kHz - 1 MHz; speeds and waits again within what vehicles do (0.5-20 m/s, 1-10 s). The
    strip finally solves the count, clipped to its range. The system's rates thus change only
    where its drive cannot give the paper's cloud size.
    """
    lo_l, hi_l = STRIP_RANGE
    target = cond.points

    def points(scanners: tuple[Scanner, ...], plan: DrivePlan, length: float) -> float:
        t_move = moving_seconds(plan, length)
        waits = np.array([s.seconds for s in plan.stops])
        return float(sum(sc.pulse_hz * (m * t_move + float(np.dot(st, waits)))
                         for sc, m, st in zip(scanners, moving, standing, strict=True)))

    def solve(scanners: tuple[Scanner, ...], plan: DrivePlan) -> float:
        """Strip length (m) giving the target count (bisection: points grow with length)."""
        a, b = 1e-3, 1e4
        if points(scanners, plan, a) >= target:
            return a
        if points(scanners, plan, b) <= target:
            return b
        for _ in range(60):
            mid = np.sqrt(a * b)
            a, b = (mid, b) if points(scanners, plan, mid) < target else (a, mid)
        return float(np.sqrt(a * b))

    def pulled(plan: DrivePlan, f: float, speeds: tuple[float, float]) -> DrivePlan:
        lo_v, hi_v = min(speeds[0], *(p.speed for p in plan.passes)), max(
            speeds[1], *(p.speed for p in plan.passes))
        passes = tuple(replace(p, speed=float(np.clip(p.speed * f, lo_v, hi_v)))
                       for p in plan.passes)
        stops = tuple(replace(s, seconds=float(np.clip(s.seconds / f, 1.0, 10.0)))
                      for s in plan.stops)
        return replace(plan, passes=passes, stops=stops)

    def bisect(make: Callable[[float], tuple[tuple[Scanner, ...], DrivePlan]]
               ) -> tuple[tuple[Scanner, ...], DrivePlan]:
        """``make(f)`` whose strip meets the drawn one (a larger f gives fewer points, so a
        longer strip for the same count)."""
        a, b = np.log(1 / 40), np.log(40)
        for _ in range(40):
            mid = 0.5 * (a + b)
            a, b = (mid, b) if solve(*make(float(np.exp(mid)))) < drive.strip else (a, mid)
        return make(float(np.exp(0.5 * (a + b))))

    scanners, plan = system.scanners, drive
    length = solve(scanners, plan)
    while (length < lo_l and len(plan.passes) > 1
           and len(plan.passes) > len({s.pass_index for s in plan.stops})):
        plan = _drop_a_pass(plan)  # never one with a stop: the standstill is the condition's
        length = solve(scanners, plan)
    for step in ("condition speeds", "rates", "vehicle speeds"):
        if lo_l <= length <= hi_l:
            break
        if step == "rates":
            def make(f: float, sc=scanners, pl=plan) -> tuple[tuple[Scanner, ...], DrivePlan]:
                return tuple(replace(s, pulse_hz=float(np.clip(s.pulse_hz / f, 1e5, 1e6)))
                             for s in sc), pl
        else:
            speeds = cond.speed if step == "condition speeds" else (0.5, 20.0)

            def make(f: float, sc=scanners, pl=plan, v=speeds
                     ) -> tuple[tuple[Scanner, ...], DrivePlan]:
                return sc, pulled(pl, f, v)
        scanners, plan = bisect(make)
        length = solve(scanners, plan)
    return (replace(system, scanners=scanners),
            replace(plan, strip=float(np.clip(length, lo_l, hi_l))))


def _drop_a_pass(plan: DrivePlan) -> DrivePlan:
    keep_stop = {s.pass_index for s in plan.stops}
    drop = [i for i in range(len(plan.passes)) if i not in keep_stop][-1]
    passes = tuple(p for i, p in enumerate(plan.passes) if i != drop)
    stops = tuple(replace(s, pass_index=s.pass_index - (s.pass_index > drop)) for s in plan.stops)
    gaps = plan.gaps[:len(passes) - 1]
    return replace(plan, passes=passes, stops=stops, gaps=gaps)


#: The paper's three clouds (section 4, Table 1) as presets of the family.
#: A: cold and wet, slow with a standstill, two large clumps (exhaust condensation where the
#: vehicle stood, returns over standing water) plus the barrier arm; B: later that day, faster,
#: fewer outliers spread in small clumps, the arm in operation; C: warm and dry, a few returns
#: within cm of the asphalt. Each kind's weight in the mix is drawn from its range.
CONDITIONS: dict[str, Condition] = {
    "A": Condition(
        "A", share=TABLE1["A"][1] / TABLE1["A"][0], points=TABLE1["A"][0], passes=(1, 3),
        speed=(0.7, 4.0), stops=(1, 2), wet=True, cold=True,
        kinds={EXHAUST: (0.35, 0.6), WATER: (0.1, 0.25), MIST: (0.05, 0.15), ARM: (0.03, 0.1),
               MOVING: (0.02, 0.08), GLASS_MP: (0.02, 0.06), AIRBORNE: (0.01, 0.04),
               ISOLATED: (0.005, 0.02)},
        optional=frozenset({GLASS_MP}),
    ),
    "B": Condition(
        "B", share=TABLE1["B"][1] / TABLE1["B"][0], points=TABLE1["B"][0], passes=(1, 3),
        speed=(2.0, 12.0), stops=(0, 1), wet=True, cold=True,
        kinds={EXHAUST: (0.15, 0.35), WATER: (0.1, 0.25), MIST: (0.05, 0.15), ARM: (0.1, 0.3),
               MOVING: (0.05, 0.15), GLASS_MP: (0.03, 0.08), AIRBORNE: (0.05, 0.12),
               ISOLATED: (0.02, 0.05)},
        optional=frozenset({GLASS_MP}),
    ),
    "C": Condition(
        "C", share=TABLE1["C"][1] / TABLE1["C"][0], points=TABLE1["C"][0], passes=(1, 3),
        speed=(3.0, 20.0), stops=(0, 1), wet=False, cold=False,
        kinds={NEAR_SURFACE: (0.55, 0.8), ISOLATED: (0.1, 0.3), AIRBORNE: (0.05, 0.15)},
    ),
}
