"""The detector registry: one entry per detector name, shared by the pipeline, CLI and service.

Adding a detector means adding one :class:`DetectorSpec` to :data:`DETECTORS` (and its parameter
model to ``lidar_outliers/params.py``). The algorithm modules are imported inside each ``run`` function so
that a detector still being written fails only when it is used, never at import time.
"""

from __future__ import annotations

import types
import typing
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel

from algorithms.result import DetectorResult
from lidar_outliers.cloud import Cloud
from lidar_outliers.errors import MissingDimensionError, ParameterError
from lidar_outliers.params import (
    OUTLIER_DETECTOR_BITS,
    DetachedParams,
    DrorParams,
    GroundParams,
    HeightFieldParams,
    PatchParams,
    SectionParams,
    SnowParams,
    TemporalParams,
    TransientParams,
)


@dataclass
class GroundResult:
    """Outcome of a ground filter on n points: ``is_ground`` (n,) bool and JSON-able ``info``."""

    is_ground: np.ndarray
    info: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class DetectorSpec:
    """One detector: its parameter model, how to run it and where its result goes.

    ``kind`` is ``"outlier"`` (sets bit ``bit`` of ``outlier_flags`` and writes ``<name>_score``)
    or ``"ground"`` (writes classes 2/1 instead of a bit).
    """

    name: str
    params_model: type[BaseModel]
    run: Callable[[Cloud, Any], DetectorResult | GroundResult]
    kind: Literal["outlier", "ground"]
    bit: int | None
    summary: str
    needs: tuple[str, ...] = ()

    @property
    def description(self) -> str:
        return (self.params_model.__doc__ or self.summary).strip()


def _require_gps_time(cloud: Cloud, detector: str) -> np.ndarray:
    if cloud.gps_time is None:
        raise MissingDimensionError(
            f"the {detector} detector needs gps_time, which this point format does not have "
            f"(use point format 1, 3-10, or run patch/section instead)"
        )
    return cloud.gps_time


def _run_temporal(cloud: Cloud, params: TemporalParams) -> DetectorResult:
    from algorithms.temporal import detect_temporal

    gps_time = _require_gps_time(cloud, "temporal")
    group = None if params.group_by == "none" else cloud.point_source_id
    return detect_temporal(
        cloud.xyz, gps_time, group,
        n1=params.n1, n2=params.n2, sigma=params.sigma, alpha=params.alpha,
        max_gap=params.max_gap,
    )


def _run_patch(cloud: Cloud, params: PatchParams) -> DetectorResult:
    from algorithms.patch import detect_patch

    return detect_patch(cloud.xyz, k=params.k, sigma=params.sigma, alpha=params.alpha)


def _run_section(cloud: Cloud, params: SectionParams) -> DetectorResult:
    from algorithms.section import detect_section

    return detect_section(
        cloud.xyz, section_size=params.section_size, sigma=params.sigma, alpha=params.alpha,
        max_iterations=params.max_iterations,
    )


def _run_height_field(cloud: Cloud, params: HeightFieldParams) -> DetectorResult:
    from algorithms.height_field import detect_height_field

    return detect_height_field(
        cloud.xyz, k=params.k, sigma=params.sigma, threshold=params.threshold,
        rms_weight=params.rms_weight, one_sided=params.one_sided,
    )


def _run_transient(cloud: Cloud, params: TransientParams) -> DetectorResult:
    """Transient clusters; with a trajectory also free-space evidence, ORed into one flag.

    Score: the cluster detector's (0 persistent, 1 single-epoch, 2 transient), raised to 2 where
    a beam saw through the point; critical value 1.5 either way.
    """
    from algorithms.transient import detect_transient

    gps_time = _require_gps_time(cloud, "transient")
    result = detect_transient(
        cloud.xyz, gps_time, k=params.k, radius=params.radius, min_dt=params.min_dt
    )
    if cloud.trajectory is None:
        result.info["free_space"] = "no trajectory file given"
        return result
    seen_through, fs_info = _free_space(cloud, gps_time, params)
    clusters = np.asarray(result.flagged, dtype=bool)
    flagged = clusters | seen_through
    score = np.where(seen_through, np.maximum(result.score, 2.0), result.score)
    info = dict(result.info)
    info.update(
        points_flagged_by_clusters=int(clusters.sum()),
        points_flagged_by_free_space=int(seen_through.sum()),
        points_flagged=int(flagged.sum()),
        free_space=fs_info,
    )
    return DetectorResult(score=score, flagged=flagged, critical_value=result.critical_value,
                          info=info)


def _free_space(
    cloud: Cloud, gps_time: np.ndarray, params: TransientParams
) -> tuple[np.ndarray, dict[str, Any]]:
    """(n,) bool seen-through points and the info, on the points the trajectory's time covers."""
    from algorithms.free_space import detect_free_space, scanner_origins

    traj = cloud.trajectory
    t0, t1 = float(traj[0, 0]), float(traj[-1, 0])
    covered = np.isfinite(gps_time) & (gps_time >= t0) & (gps_time <= t1)
    n_cov = int(covered.sum())
    if n_cov == 0:
        finite = gps_time[np.isfinite(gps_time)]
        lo_t, hi_t = (float(finite.min()), float(finite.max())) if finite.size else (None, None)
        span = f"{lo_t!r}..{hi_t!r}" if finite.size else "none finite"
        raise ParameterError(f"the trajectory's times {t0!r}..{t1!r} do not overlap the points' "
                             f"gps_time ({span}); both must use the same time base")
    arms = {int(a[0]): (float(a[1]), float(a[2]), float(a[3])) for a in params.lever_arms}
    index = np.flatnonzero(covered)
    origin = scanner_origins(gps_time[index], cloud.point_source_id[index], traj, arms)
    fs = detect_free_space(cloud.xyz[index], origin, radius=params.free_space_radius,
                           margin=params.free_space_margin, min_rays=params.free_space_min_rays)
    seen = np.zeros(len(cloud), dtype=bool)
    seen[index] = fs.flagged
    listed = np.isin(cloud.point_source_id[index], list(arms))
    info = {"radius": params.free_space_radius, "margin": params.free_space_margin,
            "min_rays": params.free_space_min_rays, "points_covered": n_cov,
            "points_uncovered": int(len(cloud) - n_cov),
            "points_without_lever_arm": int((~listed).sum()),
            "points_flagged": int(fs.flagged.sum())}
    return seen, info


def _run_ground(cloud: Cloud, params: GroundParams) -> GroundResult:
    from algorithms.ground import classify_ground

    out = classify_ground(cloud.xyz, **params.model_dump(exclude={"detector"}))
    return GroundResult(is_ground=np.asarray(out.is_ground, dtype=bool), info=dict(out.info))


def _sensor_origin(cloud: Cloud, origin: tuple[float, float, float]) -> np.ndarray:
    """The sensor position (file coordinates) in the cloud's local frame (xyz + origin = file)."""
    return np.asarray(origin, dtype=np.float64) - np.asarray(cloud.origin, dtype=np.float64)


def _run_dror(cloud: Cloud, params: DrorParams) -> DetectorResult:
    from algorithms.dror import detect_dror

    return detect_dror(
        cloud.xyz, origin=_sensor_origin(cloud, params.origin), multiplier=params.multiplier,
        angular_resolution=params.angular_resolution, min_radius=params.min_radius,
        k_min=params.k_min,
    )


def _run_snow(cloud: Cloud, params: SnowParams) -> DetectorResult:
    from algorithms.snow import detect_snow

    intensity = cloud.intensity
    if intensity is None:
        raise MissingDimensionError("the snow detector needs the points' intensity, which was "
                                    "not read from this file")
    return detect_snow(
        cloud.xyz, intensity, origin=_sensor_origin(cloud, params.origin),
        multiplier=params.multiplier, angular_resolution=params.angular_resolution,
        min_radius=params.min_radius, k_min=params.k_min, max_intensity=params.max_intensity,
    )


def _run_detached(cloud: Cloud, params: DetachedParams) -> DetectorResult:
    from algorithms.detached import detect_detached

    return detect_detached(
        cloud.xyz, link=params.link, link_spacing=params.link_spacing,
        max_cluster=params.max_cluster,
        k_surface=params.k_surface, below=params.below, above=params.above,
    )


DETECTORS: dict[str, DetectorSpec] = {
    "temporal": DetectorSpec(
        name="temporal",
        params_model=TemporalParams,
        run=_run_temporal,
        kind="outlier",
        bit=OUTLIER_DETECTOR_BITS["temporal"],
        summary="Moving fixed-interval smoother along each scanner's time series (eqs. 1-17).",
        needs=("gps_time",),
    ),
    "patch": DetectorSpec(
        name="patch",
        params_model=PatchParams,
        run=_run_patch,
        kind="outlier",
        bit=OUTLIER_DETECTOR_BITS["patch"],
        summary="Quadric fitted to each point's k nearest neighbours, tested with eq. 31.",
    ),
    "section": DetectorSpec(
        name="section",
        params_model=SectionParams,
        run=_run_section,
        kind="outlier",
        bit=OUTLIER_DETECTOR_BITS["section"],
        summary="One quadric per square XY section, refitted until no outlier remains.",
    ),
    "height_field": DetectorSpec(
        name="height_field",
        params_model=HeightFieldParams,
        run=_run_height_field,
        kind="outlier",
        bit=OUTLIER_DETECTOR_BITS["height_field"],
        summary="Leave-one-out local height fields with edge-aware half patches and robust sigma.",
    ),
    "ground": DetectorSpec(
        name="ground",
        params_model=GroundParams,
        run=_run_ground,
        kind="ground",
        bit=None,
        summary="Iterative TIN ground filter: class 2 (ground) or 1 for unflagged points.",
    ),
    "transient": DetectorSpec(
        name="transient",
        params_model=TransientParams,
        run=_run_transient,
        kind="outlier",
        bit=OUTLIER_DETECTOR_BITS["transient"],
        summary="Clusters seen at one moment only and attached to nothing (moving objects).",
        needs=("gps_time",),
    ),
    "dror": DetectorSpec(
        name="dror",
        params_model=DrorParams,
        run=_run_dror,
        kind="outlier",
        bit=OUTLIER_DETECTOR_BITS["dror"],
        summary="Baseline (Charron et al. 2018): too few neighbours in a range-scaled sphere.",
    ),
    "snow": DetectorSpec(
        name="snow",
        params_model=SnowParams,
        run=_run_snow,
        kind="outlier",
        bit=OUTLIER_DETECTOR_BITS["snow"],
        summary="Spinning sensors: dark points with too few neighbours in a range-scaled sphere.",
        needs=("intensity",),
    ),
    "detached": DetectorSpec(
        name="detached",
        params_model=DetachedParams,
        run=_run_detached,
        kind="outlier",
        bit=OUTLIER_DETECTOR_BITS["detached"],
        summary="Airborne: small clusters under or over the local surface's height envelope.",
    ),
}


def get_detector(name: str) -> DetectorSpec:
    """The registry entry for ``name``; ParameterError naming the known detectors otherwise."""
    from lidar_outliers.errors import ParameterError

    try:
        return DETECTORS[name]
    except KeyError:
        known = ", ".join(DETECTORS)
        raise ParameterError(f"unknown detector {name!r} (known: {known})") from None


def parameter_table(model: type[BaseModel]) -> list[dict[str, Any]]:
    """Name, type, default, range and description of each parameter of a stage model."""
    rows = []
    for name, info in model.model_fields.items():
        if name == "detector":
            continue
        bounds = []
        for meta in info.metadata:
            for attr, symbol in (("ge", ">="), ("gt", ">"), ("le", "<="), ("lt", "<")):
                value = getattr(meta, attr, None)
                if value is not None:
                    bounds.append(f"{symbol} {value}")
        rows.append(
            {
                "name": name,
                "type": _type_name(info.annotation),
                "default": info.default,
                "range": " and ".join(bounds) or None,
                "description": info.description or "",
            }
        )
    return rows


def _type_name(annotation: Any) -> str:
    origin = typing.get_origin(annotation)
    if origin is typing.Literal:
        return " | ".join(repr(a) for a in typing.get_args(annotation))
    if origin in (typing.Union, types.UnionType):
        return " | ".join(_type_name(a) for a in typing.get_args(annotation))
    return getattr(annotation, "__name__", str(annotation))
