"""One cloud of the family: draw, drive, cast, add the outliers, deliver in world coordinates."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np

from lidar_outliers.tools.simulator.family import (
    CONDITIONS,
    GROUND,
    KIND_NAMES,
    REFLECTIVITY,
    SURFACE,
    Frame,
    Street,
    System,
    condition_size,
    draw_drive,
    draw_frame,
    draw_street,
    draw_system,
    stream,
)
from lidar_outliers.tools.simulator.outliers import OutlierPlan, draw_plan, make_returns
from lidar_outliers.tools.simulator.survey import (
    Motion,
    build_motion,
    point_fractions,
    reach_margin,
    run_survey,
)

#: Trajectory file rate (Hz): every other pose sample.
TRAJECTORY_HZ = 100.0
#: The street is surveyed this much beyond the strip, so the cut can meet the count (Table 1)
#: where the estimate of the points per second fell short.
SPARE = 0.25


@dataclass
class SimulatedCloud:
    """A simulated survey: n returns sorted by gps_time, with the truth and the system's facts.

    Delivered like a real survey (world coordinates, metres): xyz (n, 3) float64; gps_time
    (n,) float64 GPS seconds of week; point_source_id (n,) uint16 scanner; intensity (n,)
    uint16; return_number, number_of_returns (n,) uint8; scan_angle (n,) float32 degrees (the
    mirror angle from the scan plane's downward direction); trajectory (m, 4) time, x, y, z of
    the vehicle's reference point at 100 Hz. Truth: is_outlier (n,) bool; kind (n,) uint8 codes
    of ``KIND_NAMES``. Facts the delivery would not carry: ``system`` (the scanners' true
    mounting, rates, noise), ``street`` and ``frame`` (the scene, local -> world), ``motion``
    (poses in the street frame), ``plan`` (the outlier sources: puddles, clumps, mist, moving
    bodies, in the street frame) and ``facts`` (all of it as JSON-able data).
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
    system: System
    street: Street
    frame: Frame
    motion: Motion
    plan: OutlierPlan
    strip: float
    facts: dict[str, Any]

    def __len__(self) -> int:
        return len(self.gps_time)

    def local(self, xyz: np.ndarray) -> np.ndarray:
        """World points (n, 3) in the street frame (x along the street, road crown at y = 0)."""
        return self.frame.to_local(xyz)

    def scene_height(self, xyz: np.ndarray) -> np.ndarray:
        """World z of the bare road or sidewalk (no texture) under each world point (n, 3)."""
        p = self.local(xyz)
        return self.street.ground_z(p[:, 0], p[:, 1]) + self.frame.origin[2]

    def lever_arms(self) -> tuple[tuple[int, float, float, float], ...]:
        """[point_source_id, forward, left, up] of each scanner from the reference point."""
        return tuple((s.source_id, *s.offset) for s in self.system.scanners)

    def pose(self) -> np.ndarray:
        """(m, 7): time, x, y, z (world), roll, pitch, heading (radians; heading from east)."""
        m = self.motion
        return np.column_stack([m.t, self.frame.to_world(m.pos), m.roll, m.pitch,
                                m.heading + self.frame.azimuth])

    def scanner_positions(self, gps_time: np.ndarray, source_id: np.ndarray) -> np.ndarray:
        """True world position (n, 3) of the scanner that fired each return (with attitude)."""
        out = np.zeros((len(gps_time), 3))
        for sc in self.system.scanners:
            m = source_id == sc.source_id
            out[m] = self.motion.place(gps_time[m], np.array(sc.offset))
        return self.frame.to_world(out)


def simulate(condition: str, seed: int, scale: float = 1.0) -> SimulatedCloud:
    """Simulate the paper's cloud A, B or C (Table 1) as surveyed by the system of ``seed``.

    The seed draws the system, street, drive, frame and the outliers' mix and shapes (ranges:
    :mod:`.family`); the condition keeps the paper's cloud size, outlier share and character.
    ``scale`` (0.01-1) shortens the strip, the stops and the braking by that factor, so the
    point count shrinks in proportion; the scanners' layout and mounting and the street do not
    change with it (the rate setting and the drive are fitted to the cut's size,
    :func:`.family.condition_size`). Steps: draw; fit the size; drive (poses at 200 Hz); draw
    the outlier sources; fire and cast every pulse that can reach the cut; cut the street at
    the paper's count; make the returns of every kind; add range noise and the ground's
    texture along the beams; number the returns; deliver in the world frame. The result is a
    pure function of (condition, seed, scale).
    """
    if condition not in CONDITIONS:
        raise ValueError(f"condition must be one of A, B, C, got {condition!r}")
    if not 0.01 <= scale <= 1.0:
        raise ValueError(f"scale must be in [0.01, 1], got {scale!r}")
    if seed < 0:
        raise ValueError(f"seed must be 0 or more, got {seed!r}")
    cond = CONDITIONS[condition]
    tag = ord(condition)
    system = draw_system(stream(seed, 1))
    street = draw_street(stream(seed, 2))
    frame = draw_frame(stream(seed, 3))
    drive = draw_drive(stream(seed, 4, tag), cond, street)
    drawn_system, drawn_drive = system, drive
    ahead = None
    for _ in range(3):  # the cut's shares depend on the strip and stops it settles on
        drawn_drive = replace(drawn_drive, strip=drive.strip, footprint=drive.footprint)
        moving, standing, ahead = point_fractions(system, street, drawn_drive, scale,
                                                  stream(seed, 5), ahead)
        # the vehicle stops where its scanners' returns, weighted by rate, fall on the place
        hz = np.array([sc.pulse_hz * m for sc, m in zip(system.scanners, moving, strict=True)])
        footprint = float(np.dot(hz, ahead) / hz.sum())
        system, drive = condition_size(drawn_system, replace(drawn_drive, footprint=footprint),
                                       moving, standing, cond)
    strip = drive.strip * scale
    extent = strip * (1 + SPARE)
    motion = build_motion(drive, street, system, scale, reach_margin(system, street), extent)
    plan = draw_plan(stream(seed, 6, tag), cond, system, street, motion, strip)
    survey = run_survey(system, street, motion, plan.bodies, extent, stream(seed, 7, tag))
    strip = cut_to_count(survey, cond.points * scale * (1 - cond.share), strip, extent)
    rng = stream(seed, 8, tag)
    rec, wanted, plan = make_returns(survey, plan, cond, system, street, motion, strip, rng)

    ray = rec["ray"]
    n = len(ray)
    o, d = survey["o"][ray], survey["d"][ray]
    kind = rec["kind"]
    r = rec["r"].copy()
    # the ground's mm texture: the beam meets the raised (or sunken) surface earlier (later)
    ground = (kind == SURFACE) & np.isin(rec["mat"], GROUND)
    hit = o[ground] + r[ground, None] * d[ground]
    lift = texture_height(hit[:, 0], hit[:, 1], street.texture)
    r[ground] -= lift / np.maximum(-d[ground, 2], 0.1)
    r += rng.normal(0.0, system.range_sigma, n)
    xyz = o + r[:, None] * d
    intensity = _intensity(r, rec["cos"], rec["mat"], rec["gain"] * system.intensity_gain, rng)
    # returns of one pulse are numbered by range
    by_pulse = np.lexsort((r, ray))
    first = np.concatenate([[True], ray[by_pulse][1:] != ray[by_pulse][:-1]])
    group = np.cumsum(first) - 1
    starts = np.flatnonzero(first)
    rank = np.arange(n) - starts[group]
    counts = np.diff(np.append(starts, n))
    ret = np.empty(n, dtype=np.uint8)
    nret = np.empty(n, dtype=np.uint8)
    ret[by_pulse] = rank + 1
    nret[by_pulse] = counts[group]

    gps = survey["t"][ray]
    src = survey["src"][ray]
    order = np.lexsort((ret, src, gps))
    kind = kind[order]
    traj_local = np.column_stack([motion.t, motion.pos])[::int(round(200 / TRAJECTORY_HZ))]
    trajectory = np.column_stack([traj_local[:, 0], frame.to_world(traj_local[:, 1:])])
    cloud = SimulatedCloud(
        xyz=frame.to_world(xyz[order]),
        gps_time=gps[order],
        point_source_id=src[order],
        intensity=intensity[order],
        return_number=ret[order],
        number_of_returns=nret[order],
        scan_angle=survey["phi"][ray][order].astype(np.float32),
        is_outlier=kind != SURFACE,
        kind=kind,
        trajectory=trajectory,
        condition=condition,
        seed=seed,
        scale=scale,
        system=system,
        street=street,
        frame=frame,
        motion=motion,
        plan=plan,
        strip=strip,
        facts={},
    )
    cloud.facts = _facts(cloud, drive_speeds=[p.speed for p in drive.passes],
                         plan=plan.facts(), wanted=wanted)
    return cloud


def cut_to_count(survey: dict[str, np.ndarray], count: float, strip: float, extent: float
                 ) -> float:
    """Cut the surveyed street [0, extent] at the length holding ``count`` returns (at least
    0.8 x the planned strip, so the stops and the outlier sources drawn on it stay in), and
    forget the returns beyond it. Returns the cut's length."""
    o, d = survey["o"], survey["d"]
    x = o[:, 0] + np.where(np.isfinite(survey["r"]), survey["r"], 0.0) * d[:, 0]
    x_dyn = o[:, 0] + np.where(np.isfinite(survey["r_dyn"]), survey["r_dyn"], 0.0) * d[:, 0]
    xs = np.sort(np.concatenate([x[np.isfinite(survey["r"])],
                                 x_dyn[np.isfinite(survey["r_dyn"])]]))
    k = int(round(count))
    length = float(xs[k]) if k < len(xs) else extent
    length = float(np.clip(length, 0.8 * strip, extent))
    survey["r"] = np.where(x <= length, survey["r"], np.inf)
    survey["r_dyn"] = np.where(x_dyn <= length, survey["r_dyn"], np.inf)
    keep = np.isfinite(survey["r"]) | np.isfinite(survey["r_dyn"]) | survey["sky"]
    for key in survey:
        survey[key] = survey[key][keep]
    survey["dyn"] = np.where(np.isfinite(survey["r_dyn"]), survey["dyn"], -1).astype(np.int16)
    return length


def texture_height(x: np.ndarray, y: np.ndarray, texture: np.ndarray) -> np.ndarray:
    """mm-scale asphalt roughness at (x, y): a sum of sinusoids (k, 4: kx, ky, phase, amp)."""
    kx, ky, ph, amp = texture.T
    out = np.empty(len(x))
    for start in range(0, len(x), 1 << 16):  # (batch, k) at a time keeps memory flat
        sl = slice(start, start + (1 << 16))
        out[sl] = np.sin(np.outer(x[sl], kx) + np.outer(y[sl], ky) + ph) @ amp
    return out


def _intensity(r: np.ndarray, cos_inc: np.ndarray, material: np.ndarray, gain: np.ndarray,
               rng: np.random.Generator) -> np.ndarray:
    """Intensity from reflectivity, incidence and range (a lidar-equation shape), 16 bit."""
    base = (REFLECTIVITY[material] * np.clip(cos_inc, 0.05, 1.0)
            * np.minimum(1.0, (6.0 / np.maximum(r, 0.1)) ** 2) * gain)
    noisy = base * rng.normal(1.0, 0.08, len(r))
    return np.clip(noisy * 65535 / 0.9, 1, 65535).astype(np.uint16)


def _facts(cloud: SimulatedCloud, drive_speeds: list[float], plan: dict,
           wanted: dict[str, int]) -> dict[str, Any]:
    s, st, m = cloud.system, cloud.street, cloud.motion
    counts = np.bincount(cloud.kind, minlength=len(KIND_NAMES))
    return {
        "system": {
            "layout": s.layout,
            "scanners": [asdict(sc) for sc in s.scanners],
            "reference_height": s.reference_height,
            "range_sigma": s.range_sigma,
            "min_range": s.min_range,
            "max_range": s.max_range,
            "vehicle": {"length": s.vehicle_length, "width": s.vehicle_width,
                        "roof": s.roof_height},
        },
        "street": {
            "strip_length": cloud.strip, "crop_y": list(st.crop_y),
            "half_width": st.half_width, "crown": st.crown, "grade": st.grade,
            "roughness": st.roughness, "curb": st.curb, "sidewalk": st.sidewalk,
            "facades": [{"side": f.side, "y": f.y, "segments": len(f.segments)}
                        for f in st.facades],
        },
        "frame": {"azimuth": cloud.frame.azimuth, "origin": list(cloud.frame.origin)},
        "drive": {
            "passes": [[float(a), float(b)] for a, b in m.passes],
            "stops": [[float(a), float(b)] for a, b in m.stops],
            "cruise_speeds": drive_speeds,
        },
        "outliers": {**plan, "wanted": wanted,
                     "counts": {KIND_NAMES[k]: int(c) for k, c in enumerate(counts)}},
    }


def facts_json(cloud: SimulatedCloud) -> str:
    return json.dumps(cloud.facts, default=float)

