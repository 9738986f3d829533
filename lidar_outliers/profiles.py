"""Sensor profiles: which default pipeline suits a file, decided from the evidence it carries.

Four kinds of sensor are told apart, each with its default pipeline:

``spinning``
    A multi-channel spinning sensor's sweep in the sensor frame (WADS, KITTI-like frames): a
    channel dimension (``ring``, ``laser_number``, ``channel`` or ``beam``) AND the sensor origin
    (0, 0, 0) inside the XY bounds. Pipeline: ``snow``, which needs the sensor origin.
``airborne``
    A sensor hundreds of metres up, looking down. Pipeline: ``detached`` (returns detached from
    the surface: nothing real lies under the terrain or floats high above everything).
``mobile``
    A scanner on a vehicle, 2-4 m over the road. Pipeline: ``transient`` then ``height_field``
    (``height_field`` alone without gps_time), as :func:`~lidar_outliers.params.default_stages`.
``terrestrial``
    A scanner standing still (tripod). Pipeline: ``height_field`` (no moving platform, so no
    ``transient``).

A file's density does not tell them apart: airborne surveys reach 50-100 points per m2 and
more, and a mobile drive seen over its bounding box can hold fewer. The evidence is physics
that holds for every survey, measured on a bounded sample of the points
(:func:`~lidar_outliers.lasio.read_profile_sample`, :mod:`algorithms.platform_evidence`):

1. **Where the laser looked.** The returns of one pulse lie on its beam; an airborne beam points
   down, within its scan half-angle of nadir. At least ``MIN_PULSES`` pulses with returns 1 m
   or more apart: ``DOWN_SHARE`` of them within 45 degrees of nadir -> airborne; at most
   ``SIDE_SHARE`` -> a ground-based scanner (mobile, or terrestrial when it stands still).
2. **How fast the platform moved.** The scan pattern's centre moves with the platform: at least
   ``AIRCRAFT_SPEED`` m/s (survey aircraft fly 50-80) -> airborne; at most ``GROUND_SPEED``
   m/s -> a ground vehicle (a car on a survey rarely exceeds it), under ``STILL_SPEED`` ->
   terrestrial. A file shorter than the one-second windows gives short windows, where the
   sweep across track inflates the speed: it then only counts as a ground vehicle's.
3. **How close the surfaces were.** At least ``NEAR_SENSOR_DENSITY`` points per m2 where the
   points are (1 m cells): only a sensor a few metres away puts that many on a surface
   (mobile; terrestrial without usable GPS time).
4. **How far from nadir it fired.** Scan angles beyond ``AIRBORNE_MAX_SCAN_ANGLE`` degrees:
   not a scanner looking down (mobile).

The first rule that has evidence decides, in that order (beam directions outrank speed: a
drone is slow but looks down). With no evidence the airborne pipeline runs: on ground-based
data it flags least (``detached`` flags no point of the simulated mobile clouds and 0.05 % of
a snow frame, where the mobile pipeline flags 4-25 % of an airborne tile's real points); the
statistics then say the evidence was weak (``profile_confidence`` low). A job can also name
the profile (``PipelineParams.profile``) instead of ``auto``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from lidar_outliers.params import default_stages, stage

#: Extra-dimension names (lower case) that mark a multi-channel spinning sensor.
CHANNEL_DIMENSIONS = frozenset({"ring", "laser_number", "channel", "beam"})

PROFILES = ("spinning", "airborne", "mobile", "terrestrial")

#: Pulses with returns far enough apart for their beam direction to count.
MIN_PULSES = 30
#: Share of beams within 45 degrees of nadir at or above which the sensor looks down.
DOWN_SHARE = 0.9
#: Share at or below which it looks sideways (a mobile profiler's clipped road strip: 0.43).
SIDE_SHARE = 0.7
#: m/s: at least this is an aircraft; at most GROUND_SPEED a ground vehicle; under STILL_SPEED
#: the platform stands still.
AIRCRAFT_SPEED = 35.0
GROUND_SPEED = 25.0
STILL_SPEED = 0.5
#: Time windows the speed needs.
MIN_SPEED_WINDOWS = 2
#: Points per m2 of the occupied 1 m cells that only a sensor a few metres away reaches.
NEAR_SENSOR_DENSITY = 1000.0
#: Degrees off nadir no airborne scanner fires at.
AIRBORNE_MAX_SCAN_ANGLE = 60.0
#: Words of the header's system identifier or generating software that name a kind of sensor
#: (a hint only, used when the points carry no evidence; processing software such as TerraScan
#: serves every kind and names none).
HEADER_HINTS: dict[str, tuple[str, ...]] = {
    "airborne": ("ALS", "ALTM", "LMS-Q", "VQ-780", "VQ-1560", "TERRAINMAPPER", "CITYMAPPER",
                 "GALAXY", "TITAN", "HAWKEYE", "CHIROPTERA", "SPL100"),
    "mobile": ("VMX", "VMQ", "LYNX", "PEGASUS", "MX2", "MX9", "MX50", "MMS"),
    "terrestrial": ("RISCAN", "SCANSTATION", "CYCLONE", "FARO", "RTC360", "Z+F"),
    "spinning": ("VELODYNE", "OUSTER", "HESAI", "HDL-", "VLP-"),
}

Confidence = Literal["high", "medium", "low"]


@dataclass(frozen=True)
class ProfileChoice:
    """The profile chosen for a file, why (``reason``, and ``basis`` in a few words), how sure,
    and the evidence used (JSON-able)."""

    profile: str
    reason: str
    confidence: Confidence
    evidence: dict[str, Any] = field(default_factory=dict)
    basis: str = ""


def profile_evidence(facts: Mapping[str, Any], sample: Any = None) -> dict[str, Any]:
    """The evidence :func:`choose_profile` decides on, as plain numbers.

    facts : the header facts (``LasFacts.to_dict()`` or :func:`~lidar_outliers.pipeline.
    cloud_facts`): ``extra_dimensions``, ``bounds``, ``points``, ``crs``, ``system_identifier``,
    ``generating_software``; missing keys count as absent. sample : a
    :class:`~lidar_outliers.lasio.ProfileSample` of the points, or None (header facts only).

    Returns a dict: ``points_per_m2`` (of the XY bounds, for information),
    ``channel_dimensions``, ``sensor_origin_inside_xy_bounds``, ``sampled_points``,
    ``speed_m_s`` (+ ``speed_quartiles_m_s``, ``speed_windows``), ``pulses``,
    ``beams_down_share``, ``beam_nadir_angle_deg``, ``occupied_points_per_m2``,
    ``scan_angle_max_deg``, ``usable_gps_time``, ``geographic`` and the header's
    ``system_identifier`` / ``generating_software``.
    """
    from algorithms import platform_evidence as pe

    names = sorted({str(n).lower() for n in facts.get("extra_dimensions") or []}
                   & CHANNEL_DIMENSIONS)
    bounds = facts.get("bounds") or {}
    lo, hi = bounds.get("min"), bounds.get("max")
    inside = density = None
    if lo is not None and hi is not None:
        inside = bool(lo[0] <= 0.0 <= hi[0] and lo[1] <= 0.0 <= hi[1])
        area = max(float(hi[0]) - float(lo[0]), 0.0) * max(float(hi[1]) - float(lo[1]), 0.0)
        density = round(int(facts.get("points") or 0) / area, 3) if area > 0 else None
    geographic = bool(facts.get("geographic"))
    out: dict[str, Any] = {
        "points_per_m2": density,
        "channel_dimensions": names,
        "sensor_origin_inside_xy_bounds": inside,
        "system_identifier": facts.get("system_identifier") or "",
        "generating_software": facts.get("generating_software") or "",
        "geographic": geographic,
        "sampled_points": 0,
        "usable_gps_time": None,
        "speed_m_s": None, "speed_quartiles_m_s": None, "speed_windows": 0,
        "speed_short_windows": False,
        "pulses": 0, "beams_down_share": None, "beam_nadir_angle_deg": None,
        "occupied_points_per_m2": None,
        "scan_angle_max_deg": None,
    }
    if sample is None or len(sample) == 0:
        return out
    out["sampled_points"] = len(sample)
    t = sample.gps_time
    timed = pe.usable_time(t)
    out["usable_gps_time"] = timed
    if not geographic:  # metres: speeds and densities mean something
        out["occupied_points_per_m2"] = _round(pe.occupied_density(sample.xyz[:, :2]), 1)
        if timed:
            speed = pe.platform_speed(t, sample.xyz[:, :2], sample.source)
            out["speed_m_s"] = _round(speed.speed, 2)
            if speed.speed is not None:
                out["speed_quartiles_m_s"] = [_round(speed.low, 2), _round(speed.high, 2)]
            out["speed_windows"] = speed.windows
            out["speed_short_windows"] = speed.short
            if sample.return_number is not None:
                beams = pe.pulse_directions(t, sample.xyz, sample.return_number, sample.source)
                out["pulses"] = beams.pulses
                out["beams_down_share"] = _round(beams.down_share, 3)
                out["beam_nadir_angle_deg"] = _round(beams.median_nadir_angle, 1)
    out["scan_angle_max_deg"] = _round(pe.scan_angle_extent(sample.scan_angle), 2)
    return out


def file_evidence(path: Any, facts: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """:func:`profile_evidence` of a LAS/LAZ file: its header facts (``facts``, or read with
    :func:`~lidar_outliers.lasio.inspect_las`) and a bounded sample of its points
    (:func:`~lidar_outliers.lasio.read_profile_sample`)."""
    from lidar_outliers.lasio import inspect_las, read_profile_sample

    if facts is None:
        facts = inspect_las(path).to_dict()
    return profile_evidence(facts, read_profile_sample(path))


def _round(value: float | None, digits: int) -> float | None:
    return None if value is None else round(float(value), digits)


def choose_profile(evidence: Mapping[str, Any]) -> ProfileChoice:
    """The profile for a file from its :func:`profile_evidence` (rules of the module docstring).

    >>> choose_profile({"channel_dimensions": ["ring"], "sensor_origin_inside_xy_bounds": True}
    ...                ).profile
    'spinning'
    >>> choose_profile({"pulses": 5148, "beams_down_share": 1.0, "speed_m_s": 2.0,
    ...                 "speed_windows": 9}).profile
    'airborne'
    >>> choose_profile({"speed_m_s": 9.5, "speed_windows": 40}).profile
    'mobile'
    >>> choose_profile({}).confidence
    'low'
    """
    ev = dict(evidence)
    names = ev.get("channel_dimensions") or []
    pulses = int(ev.get("pulses") or 0)
    down = ev.get("beams_down_share")
    speed = ev.get("speed_m_s")
    windows = int(ev.get("speed_windows") or 0)
    occupied = ev.get("occupied_points_per_m2")
    scan = ev.get("scan_angle_max_deg")
    short = bool(ev.get("speed_short_windows"))
    measured = speed is not None and windows >= MIN_SPEED_WINDOWS and not short
    # A short-window speed is inflated by the sweep across track: an upper bound only.
    bounded = speed is not None and windows >= 1 and short
    still = measured and speed < STILL_SPEED
    timed = ev.get("usable_gps_time")

    def pick(profile: str, reason: str, confidence: Confidence, basis: str) -> ProfileChoice:
        return ProfileChoice(profile, reason, confidence, ev, basis)

    def ground(why: str, confidence: Confidence, basis: str) -> ProfileChoice:
        if still:
            return pick("terrestrial", f"{why}; the sensor stood still ({speed:g} m/s)",
                        confidence, f"{basis}, still")
        return pick("mobile", why, confidence, basis)

    if names and ev.get("sensor_origin_inside_xy_bounds"):
        return pick("spinning", f"channel dimension {', '.join(names)} and the sensor origin "
                    "(0, 0, 0) inside the XY bounds", "high", "channels around the origin")
    if pulses >= MIN_PULSES and down is not None:
        share = f"{100 * down:.0f} % of {pulses} pulses' beams within 45 deg of nadir"
        beams = f"{100 * down:.0f} % of beams down"
        if down >= DOWN_SHARE:
            return pick("airborne", f"{share}: a sensor looking down", "high", beams)
        if down <= SIDE_SHARE:
            return ground(f"{share}: a scanner looking sideways", "high", beams)
    if measured and speed >= AIRCRAFT_SPEED:
        return pick("airborne", f"platform speed {speed:g} m/s (>= {AIRCRAFT_SPEED:g}: an "
                    "aircraft)", "high", f"{speed:.0f} m/s")
    if measured and speed <= GROUND_SPEED:
        return ground(f"platform speed {speed:g} m/s (<= {GROUND_SPEED:g}: a ground vehicle, "
                      "no pulse directions)", "medium", f"{speed:.1f} m/s")
    if bounded and speed <= GROUND_SPEED:
        return pick("mobile", f"platform speed at most {speed:g} m/s over the file's "
                    f"{windows} short stretch(es) of time (<= {GROUND_SPEED:g}: a ground vehicle)",
                    "low", f"<= {speed:.1f} m/s")
    if occupied is not None and occupied >= NEAR_SENSOR_DENSITY:
        why = (f"{occupied:g} points per m2 where there are points (>= "
               f"{NEAR_SENSOR_DENSITY:g}: surfaces a few metres from the sensor)")
        basis = f"{occupied:.0f} points/m2 near the sensor"
        if timed is False:
            return pick("terrestrial", f"{why}, no usable GPS time", "medium",
                        f"{basis}, no time")
        return pick("mobile", why, "medium", basis)
    if scan is not None and scan > AIRBORNE_MAX_SCAN_ANGLE:
        return pick("mobile", f"scan angles up to {scan:g} deg (> {AIRBORNE_MAX_SCAN_ANGLE:g}: "
                    "not a scanner looking down)", "low", f"scan angles to {scan:.0f} deg")
    hinted = header_hint(ev.get("system_identifier", ""), ev.get("generating_software", ""))
    if hinted is not None and hinted[0] != "spinning":  # snow needs the sensor-frame test
        return pick(hinted[0], f"no evidence in the points; the header names {hinted[1]!r}",
                    "low", f"header {hinted[1]!r}")
    if names:
        why = (f"channel dimension {', '.join(names)} but the sensor origin is outside the XY "
               "bounds, and no other evidence")
    else:
        why = "no evidence of the platform (no pulse directions, speed or near-sensor density)"
    return pick("airborne", f"{why}: the airborne pipeline, which flags least when wrong", "low",
                "no evidence")


def header_hint(*texts: str) -> tuple[str, str] | None:
    """(profile, word) for the first of ``HEADER_HINTS`` found as a word of ``texts``."""
    import re

    words = " ".join(texts).upper()
    for profile, names in HEADER_HINTS.items():
        for name in names:
            # a model number may follow (ALS70, and Leica's "ALSxx" placeholder)
            if re.search(rf"(?<![A-Z0-9]){re.escape(name)}[0-9X]*(?![A-Z])", words):
                return profile, name
    return None


def profile_stages(profile: str, has_gps_time: bool) -> list:
    """The default pipeline of a profile (a list of stage parameter models, all defaults)."""
    if profile == "spinning":
        return [stage("snow")]
    if profile == "airborne":
        return [stage("detached")]
    if profile == "mobile":
        return default_stages(has_gps_time)
    if profile == "terrestrial":
        return [stage("height_field")]
    raise ValueError(f"unknown profile {profile!r} (known: {', '.join(PROFILES)})")


def default_pipeline(evidence: Mapping[str, Any]) -> tuple[str, list]:
    """(profile, stages) for a job that names no pipeline."""
    profile = choose_profile(evidence).profile
    return profile, profile_stages(profile, bool(evidence.get("usable_gps_time")))


def sample_cloud(cloud: Any, max_points: int = 250_000, run_points: int = 2_500) -> Any:
    """A :class:`~lidar_outliers.lasio.ProfileSample` of an in-memory
    :class:`~lidar_outliers.cloud.Cloud` (runs of consecutive points, as from a file; a cloud
    has no return numbers or scan angles)."""
    from lidar_outliers.lasio import ProfileSample

    n = len(cloud)
    if n <= max_points:
        index = np.arange(n)
        runs = 1 if n else 0
    else:
        runs = max(1, max_points // run_points)
        starts = np.arange(runs) * (n // runs)
        index = (starts[:, None] + np.arange(run_points)).ravel()
    return ProfileSample(
        xyz=cloud.xyz[index], origin=np.asarray(cloud.origin, dtype=np.float64),
        gps_time=None if cloud.gps_time is None else cloud.gps_time[index],
        return_number=None, number_of_returns=None,
        source=np.asarray(cloud.point_source_id[index], dtype=np.int64) * 16,
        scan_angle=None, points_in_file=n, runs=runs,
    )
