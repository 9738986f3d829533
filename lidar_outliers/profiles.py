"""Sensor profiles: which default pipeline suits a file, decided from its header and point layout.

One documented profile per sensor kind, chosen from the file's header and point layout, never
parameters tuned per file. Three kinds are told apart:

``spinning``
    A multi-channel spinning sensor's sweep stored in the sensor frame (WADS, KITTI-like
    frames): the file has a channel dimension (an extra dimension called ``ring``,
    ``laser_number``, ``channel`` or ``beam``) AND the sensor origin (0, 0, 0) lies inside the
    XY bounds. Default pipeline: ``snow`` (dark and sparse in a range-scaled sphere), which
    needs the sensor origin, hence the frame test.
``airborne``
    Sparse clouds: fewer than ``AIRBORNE_MAX_DENSITY`` points per square metre of the XY
    bounding box (airborne tiles have 0.05-50; a mobile-mapping strip has thousands near the
    vehicle). Default pipeline: ``detached`` (small clusters outside the surface's envelope).
``mobile``
    Everything else (mobile mapping, terrestrial): ``transient`` (moving objects; with a
    trajectory file it also uses free-space evidence) then ``height_field`` (``height_field``
    alone without gps_time), as :func:`~lidar_outliers.params.default_stages`. The paper's
    ``temporal`` then ``patch`` stays available by naming it
    (:func:`~lidar_outliers.params.paper_stages`).

A job can also name the profile (``PipelineParams.profile``) instead of ``auto``.

The facts are those the statistics already report for the input (``extra_dimensions``,
``bounds``, ``points``, ``has_gps_time``), so the choice can be printed beside the result.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from lidar_outliers.params import default_stages, stage

#: Points per square metre of the XY bounding box below which a cloud is taken as airborne.
AIRBORNE_MAX_DENSITY = 50.0

#: Extra-dimension names (lower case) that mark a multi-channel spinning sensor.
CHANNEL_DIMENSIONS = frozenset({"ring", "laser_number", "channel", "beam"})

PROFILES = ("spinning", "airborne", "mobile")


def choose_profile(facts: Mapping[str, Any]) -> str:
    """``spinning``, ``airborne`` or ``mobile`` for a file described by ``facts``.

    facts : mapping with ``extra_dimensions`` (list of names), ``bounds`` (``{"min": [x, y, z],
    "max": [x, y, z]}`` in file coordinates) and ``points`` (int); missing keys count as absent.

    >>> choose_profile({"extra_dimensions": ["ring"], "points": 114182,
    ...                 "bounds": {"min": [-80, -70, -3], "max": [313, 80, 19]}})
    'spinning'
    >>> choose_profile({"extra_dimensions": [], "points": 37805,
    ...                 "bounds": {"min": [698000, 6259243, 12], "max": [699000, 6260000, 266]}})
    'airborne'
    >>> choose_profile({"extra_dimensions": [], "points": 1077987,
    ...                 "bounds": {"min": [0, 0, 0], "max": [15, 12.3, 4.6]}})
    'mobile'
    """
    names = {str(n).lower() for n in facts.get("extra_dimensions") or []}
    bounds = facts.get("bounds") or {}
    lo, hi = bounds.get("min"), bounds.get("max")
    if names & CHANNEL_DIMENSIONS and lo is not None and hi is not None:
        if lo[0] <= 0.0 <= hi[0] and lo[1] <= 0.0 <= hi[1]:
            return "spinning"
    if lo is not None and hi is not None:
        area = max(float(hi[0]) - float(lo[0]), 0.0) * max(float(hi[1]) - float(lo[1]), 0.0)
        points = int(facts.get("points") or 0)
        if area > 0 and points / area < AIRBORNE_MAX_DENSITY:
            return "airborne"
    return "mobile"


def profile_evidence(facts: Mapping[str, Any]) -> dict[str, Any]:
    """The facts :func:`choose_profile` used, and its decision in words (for the statistics).

    Returns ``{"profile", "reason", "channel_dimensions", "sensor_origin_inside_xy_bounds",
    "points_per_m2"}`` (the last two None when the bounds are unknown).
    """
    profile = choose_profile(facts)
    names = sorted({str(n).lower() for n in facts.get("extra_dimensions") or []}
                   & CHANNEL_DIMENSIONS)
    bounds = facts.get("bounds") or {}
    lo, hi = bounds.get("min"), bounds.get("max")
    inside = density = None
    if lo is not None and hi is not None:
        inside = bool(lo[0] <= 0.0 <= hi[0] and lo[1] <= 0.0 <= hi[1])
        area = max(float(hi[0]) - float(lo[0]), 0.0) * max(float(hi[1]) - float(lo[1]), 0.0)
        density = round(int(facts.get("points") or 0) / area, 3) if area > 0 else None
    if profile == "spinning":
        reason = (f"channel dimension {', '.join(names)} and the sensor origin (0, 0, 0) "
                  f"inside the XY bounds")
    elif profile == "airborne":
        reason = f"{density} points per m2 of the XY bounds (< {AIRBORNE_MAX_DENSITY:g})"
    else:
        why = []
        if names:
            why.append(f"channel dimension {', '.join(names)} but the sensor origin is outside "
                       f"the XY bounds")
        else:
            why.append("no channel dimension")
        if density is None:
            why.append("XY bounds unknown or flat")
        else:
            why.append(f"{density} points per m2 (>= {AIRBORNE_MAX_DENSITY:g})")
        reason = ", ".join(why)
    return {"profile": profile, "reason": reason, "channel_dimensions": names,
            "sensor_origin_inside_xy_bounds": inside, "points_per_m2": density}


def profile_stages(profile: str, has_gps_time: bool) -> list:
    """The default pipeline of a profile (a list of stage parameter models, all defaults)."""
    if profile == "spinning":
        return [stage("snow")]
    if profile == "airborne":
        return [stage("detached")]
    if profile == "mobile":
        return default_stages(has_gps_time)
    raise ValueError(f"unknown profile {profile!r} (known: {', '.join(PROFILES)})")


def default_pipeline(facts: Mapping[str, Any]) -> tuple[str, list]:
    """(profile, stages) for a job that names no pipeline."""
    profile = choose_profile(facts)
    return profile, profile_stages(profile, bool(facts.get("has_gps_time")))
