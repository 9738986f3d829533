"""Detector and pipeline parameters: one pydantic model per detector.

These models are the single source of truth for parameter names, defaults and ranges. The command
line (`lidar-outliers detect`, `lidar-outliers detectors`) and the web service (`/processes`) are
both generated from them, so a parameter is spelt the same everywhere.

Every model forbids unknown fields, so a typo such as ``{"n_1": 5}`` is refused with a message that
names the field instead of being silently ignored.
"""

from __future__ import annotations

import json
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from lidar_outliers.errors import ParameterError

Auto = Literal["auto"]


class _Stage(BaseModel):
    model_config = ConfigDict(extra="forbid")


class TemporalParams(_Stage):
    """Algorithm (a): moving fixed-interval smoother along scan lines (eqs. 1-17)."""

    detector: Literal["temporal"] = "temporal"
    n1: int = Field(5, ge=1, le=100, description="Points before the tested point in the window.")
    n2: int = Field(5, ge=1, le=100, description="Points after the tested point in the window.")
    sigma: float | Auto = Field(
        "auto",
        description="Standard deviation of each coordinate in metres (> 0), or 'auto' for a robust "
        "estimate from the data (reported in the statistics).",
    )
    alpha: float = Field(0.001, gt=0.0, lt=0.5, description="Two-sided significance level.")
    max_gap: float | Auto = Field(
        "auto",
        description="Time step in seconds (> 0) above which a scan line is split into segments; "
        "'auto' = 5 x the group's median positive time step.",
    )
    group_by: Literal["point_source_id", "none"] = Field(
        "point_source_id", description="Dimension that separates the scanners, or 'none'."
    )

    @model_validator(mode="after")
    def _positive_numbers(self) -> TemporalParams:
        _require_positive(self.sigma, "sigma")
        _require_positive(self.max_gap, "max_gap")
        if self.n1 + self.n2 < 3:
            # A quadratic in time (eqs. 1-3) needs three neighbours besides the tested point,
            # otherwise the point carries the whole fit and eq. 15 divides by zero.
            raise ValueError(f"n1 + n2 must be at least 3, got {self.n1} + {self.n2}")
        return self


class PatchParams(_Stage):
    """Algorithm (b): quadric (eqs. 18-31) fitted to the k nearest neighbours of each point."""

    detector: Literal["patch"] = "patch"
    k: int = Field(
        40, ge=10, le=500, description="Neighbours per patch, the point itself included."
    )
    sigma: float = Field(
        0.005, gt=0.0, description="Coordinate standard deviation in metres (D_ii = sigma^2 I)."
    )
    alpha: float = Field(0.001, gt=0.0, lt=0.5, description="Two-sided significance level.")


class SectionParams(_Stage):
    """Algorithm (c): one quadric per square XY section, refitted until no outlier remains."""

    detector: Literal["section"] = "section"
    section_size: float = Field(5.0, gt=0.0, le=10000.0, description="Section edge in metres.")
    sigma: float = Field(
        0.005, gt=0.0, description="Coordinate standard deviation in metres (D_ii = sigma^2 I)."
    )
    alpha: float = Field(0.001, gt=0.0, lt=0.5, description="Two-sided significance level.")
    max_iterations: int = Field(10, ge=1, le=1000, description="Refits per section at most.")


class GroundParams(_Stage):
    """Iterative TIN-based ground filter: step-edge triangles by slope, adjust, repeat."""

    detector: Literal["ground"] = "ground"
    slope_threshold: float = Field(
        35.0, gt=0.0, lt=90.0,
        description="Triangle slope in degrees above which it is a step edge.",
    )
    max_iterations: int = Field(
        1000, ge=1, le=10000,
        description="Adjust-and-retest rounds at most (one round peels one ring off an object).",
    )
    min_object_height: float = Field(
        0.5, ge=0.0, le=100.0,
        description="Metres: least rise of a step edge; points lowered by less are ground.",
    )
    low_outlier_depth: float = Field(
        2.0, gt=0.0, le=1000.0,
        description="Metres below the lower quartile of its ~24 neighbours that makes a "
        "point a low outlier (object).",
    )
    max_object_size: float = Field(
        25.0, ge=0.0, le=1000.0,
        description="Metres: largest window of the progressive opening of the lowest-point "
        "raster; raised ground wider than this is terrain; 0 turns the terrace check off.",
    )
    terrain_slope: float = Field(
        0.2, ge=0.0, le=10.0,
        description="tan of the steepest terrain slope: the progressive opening calls a cell "
        "object when a window of radius r lowers it by more than terrain_slope x r.",
    )
    ground_tolerance: float = Field(
        0.5, ge=0.0, le=100.0,
        description="Metres: final step, a point less than this (+ 1.0 x local grade) above the "
        "surface interpolated from the ground points is ground; 0 turns the step off.",
    )
    tin_cell: float = Field(
        0.05, ge=0.0, le=10.0,
        description="Metres: only the lowest point per XY cell of this size enters the TIN "
        "(thins dense mobile clouds; airborne clouds keep every point); 0: per exact XY position.",
    )


class HeightFieldParams(_Stage):
    """Mobile-mapping (b): leave-one-out height fields on k neighbours and four half patches."""

    detector: Literal["height_field"] = "height_field"
    k: int = Field(24, ge=8, le=200, description="Neighbours per patch, the point excluded.")
    sigma: float | Auto = Field(
        "auto",
        description="Coordinate standard deviation in metres (> 0), or 'auto' for the MAD of the "
        "cloud's full-patch studentised residuals (reported in the statistics).",
    )
    threshold: float = Field(
        9.0, gt=0.0, le=1000.0, description="Score (in sigmas) above which a point is flagged."
    )
    rms_weight: float = Field(
        0.5, ge=0.0, le=100.0,
        description="Weight of a fit's own residual standard error: a patch of scattered points "
        "cannot vouch for its members.",
    )
    one_sided: bool = Field(
        True,
        description="On ground-like patches (normal within 45 degrees of vertical) count only "
        "points above the surface (early returns).",
    )

    @model_validator(mode="after")
    def _positive_sigma(self) -> HeightFieldParams:
        _require_positive(self.sigma, "sigma")
        return self


class DrorParams(_Stage):
    """Baseline: dynamic-radius outlier removal (Charron et al. 2018) for spinning sensors."""

    detector: Literal["dror"] = "dror"
    multiplier: float = Field(4.0, gt=0.0, le=100.0, description="Radius = multiplier x range x "
                              "angular_resolution (at least min_radius).")
    angular_resolution: float = Field(
        0.2, gt=0.0, le=10.0, description="Sensor's horizontal angular step in degrees."
    )
    min_radius: float = Field(0.04, ge=0.0, le=100.0, description="Least search radius, metres.")
    k_min: int = Field(
        2, ge=1, le=1000, description="Fewer other points than this in the sphere: noise."
    )
    origin: tuple[float, float, float] = Field(
        (0.0, 0.0, 0.0),
        description="Sensor position in the file's coordinates (0, 0, 0 for a cloud stored in "
        "the sensor frame, as spinning-sensor frames are).",
    )


class SnowParams(_Stage):
    """Spinning sensors: falling snow = dark (low intensity) AND sparse in a dynamic radius."""

    detector: Literal["snow"] = "snow"
    multiplier: float = Field(4.0, gt=0.0, le=100.0, description="Radius = multiplier x range x "
                              "angular_resolution (at least min_radius).")
    angular_resolution: float = Field(
        0.2, gt=0.0, le=10.0, description="Sensor's horizontal angular step in degrees."
    )
    min_radius: float = Field(0.04, ge=0.0, le=100.0, description="Least search radius, metres.")
    k_min: int = Field(
        4, ge=1, le=1000, description="Fewer other points than this in the sphere: snow."
    )
    max_intensity: float = Field(
        0.0, ge=0.0, le=65535.0, description="Points with intensity at most this are candidates."
    )
    origin: tuple[float, float, float] = Field(
        (0.0, 0.0, 0.0),
        description="Sensor position in the file's coordinates (0, 0, 0 for the sensor frame).",
    )


class DetachedParams(_Stage):
    """Airborne: small clusters lying under or over the local surface's height envelope."""

    detector: Literal["detached"] = "detached"
    link: float = Field(
        3.0, gt=0.0, le=1000.0,
        description="Metres: points closer than max(link, link_spacing x median spacing) form one "
        "cluster.",
    )
    link_spacing: float = Field(
        4.0, ge=0.0, le=1000.0,
        description="Multiple of the cloud's median nearest-neighbour distance for the link.",
    )
    max_cluster: int = Field(
        10, ge=1, le=1000, description="Clusters of at most this many points are tested."
    )
    k_surface: int = Field(
        128, ge=3, le=2000, description="Surface points (nearest in XY) for the local plane."
    )
    below: float = Field(
        1.0, gt=0.0, le=1000.0, description="Metres under the lowest surface residual: outlier."
    )
    above: float = Field(
        10.0, gt=0.0, le=1000.0, description="Metres over the highest surface residual: outlier."
    )


class TransientParams(_Stage):
    """Mobile mapping: single-epoch clusters attached to nothing (moving objects)."""

    detector: Literal["transient"] = "transient"
    k: int = Field(24, ge=1, le=200, description="Neighbours searched per point.")
    radius: float = Field(
        0.2, gt=0.0, le=100.0,
        description="Metres: neighbours this close count; clusters link at this distance.",
    )
    min_dt: float = Field(
        0.5, gt=0.0, le=1e6,
        description="Seconds: a neighbour recorded this much earlier or later makes a point "
        "persistent (seen again by the other scanner or on another pass).",
    )
    free_space_radius: float = Field(
        0.006, gt=0.0, le=10.0,
        description="With a trajectory file: metres a beam must pass within a point to see "
        "through it (free-space evidence).",
    )
    free_space_margin: float = Field(
        0.08, ge=0.0, le=100.0,
        description="With a trajectory file: metres a beam must end beyond a point to count.",
    )
    free_space_min_rays: int = Field(
        1, ge=1, le=1000,
        description="With a trajectory file: beams that saw through a point to flag it.",
    )
    lever_arms: list[tuple[int, float, float, float]] = Field(
        [(1, -0.6, 0.45, 0.0), (2, -0.6, -0.45, 0.0)],
        description="With a trajectory file: [point_source_id, forward, left, up] metres of "
        "each scanner from the trajectory's reference point in the vehicle frame (heading from "
        "the trajectory's motion). Default: the simulator's two scanners (trajectory = roof "
        "point at scanner height). Scanners not listed sit at the reference point.",
    )


def _require_positive(value: float | str, name: str) -> None:
    if not isinstance(value, str) and not value > 0:
        raise ValueError(f"{name} must be > 0 or 'auto', got {value!r}")


#: Outlier detectors, by name, with their bit in the ``outlier_flags`` extra dimension.
OUTLIER_DETECTOR_BITS: dict[str, int] = {
    "temporal": 1, "patch": 2, "section": 4, "height_field": 64, "transient": 128,
    "dror": 8, "snow": 16, "detached": 32,
}

Stage = Annotated[
    TemporalParams | PatchParams | SectionParams | GroundParams | HeightFieldParams
    | TransientParams | DrorParams | SnowParams | DetachedParams,
    Field(discriminator="detector"),
]

STAGE_MODELS: dict[str, type[_Stage]] = {
    "temporal": TemporalParams,
    "patch": PatchParams,
    "section": SectionParams,
    "ground": GroundParams,
    "height_field": HeightFieldParams,
    "transient": TransientParams,
    "dror": DrorParams,
    "snow": SnowParams,
    "detached": DetachedParams,
}


class PipelineParams(BaseModel):
    """An ordered list of stages; a later stage sees only the points earlier stages did not flag."""

    model_config = ConfigDict(extra="forbid")

    pipeline: list[Stage] | None = Field(
        None,
        description="Stages in order. Default: chosen by the sensor profile (see 'profile'); "
        "the paper's pipeline is [temporal, patch].",
    )
    profile: Literal["auto", "mobile", "spinning", "airborne"] = Field(
        "auto",
        description="Sensor kind whose default pipeline runs when 'pipeline' is not given: "
        "spinning -> snow; airborne -> detached; mobile -> transient then height_field "
        "(height_field alone without gps_time). 'auto' decides from the file's header and "
        "point layout (lidar_outliers/profiles.py); ignored when 'pipeline' is given.",
    )
    classify: bool = Field(
        True, description="Write noise_class to flagged points (and 2/1 for ground)."
    )
    noise_class: int = Field(
        7, ge=0, le=255, description="ASPRS class for flagged points (7 or 18)."
    )
    reference_classes: list[int] | None = Field(
        None,
        description="Input classes taken as truth (e.g. [7, 18] for noise, [2] for ground); adds "
        "confusion counts to the statistics.",
    )

    @model_validator(mode="before")
    @classmethod
    def _empty_pipeline_is_default(cls, data: Any) -> Any:
        if isinstance(data, dict) and data.get("pipeline") == []:
            raise ValueError("pipeline must name at least one stage")
        return data


def default_stages(has_gps_time: bool) -> list[_Stage]:
    """The mobile-mapping profile's default pipeline (``lidar_outliers.profiles``; issue 5's detectors).

    ``transient`` (moving objects; it needs gps_time) then ``height_field``; ``height_field``
    alone for a file without usable gps_time.
    """
    if has_gps_time:
        return [TransientParams(), HeightFieldParams()]
    return [HeightFieldParams()]


def paper_stages(has_gps_time: bool) -> list[_Stage]:
    """The paper's pipeline (Table 5): temporal then patch; patch alone without gps_time."""
    if has_gps_time:
        return [TemporalParams(), PatchParams()]
    return [PatchParams()]


# --------------------------------------------------------------------------- validation


def validation_message(exc: ValidationError, *, option_style: bool = False) -> str:
    """One line naming the offending field(s) of a pydantic error.

    ``pipeline.0.temporal.n1`` becomes ``pipeline[0].n1`` (or ``--n1`` with ``option_style``).
    """
    parts: list[str] = []
    seen: set[tuple[str, ...]] = set()
    for err in exc.errors():
        loc = [str(x) for x in err.get("loc", ())]
        # A union reports one error per member, tagged with the member type: keep the field,
        # once.
        while loc and (loc[-1] in _TYPE_TAGS or "[" in loc[-1]):
            loc.pop()
        if tuple(loc) in seen:
            continue
        seen.add(tuple(loc))
        # The discriminated union inserts the detector name after the index: drop it.
        cleaned: list[str] = []
        for i, item in enumerate(loc):
            if i > 0 and loc[i - 1].isdigit() and item in _stage_names():
                continue
            cleaned.append(f"[{item}]" if item.isdigit() else item)
        name = ".".join(cleaned).replace(".[", "[") or "parameters"
        if option_style and cleaned:
            name = "--" + cleaned[-1].replace("_", "-")
        msg = err.get("msg", "invalid value")
        msg = msg.removeprefix("Value error, ")
        if err.get("type") == "extra_forbidden":
            msg = "unknown parameter"
        elif err.get("type") == "union_tag_not_found":
            msg = f"each stage needs a \"detector\" key (one of: {', '.join(_stage_names())})"
        elif err.get("type") == "union_tag_invalid":
            tag = (err.get("ctx") or {}).get("tag", err.get("input"))
            msg = f"unknown detector {tag!r} (known: {', '.join(_stage_names())})"
        elif "input" in err and err.get("type") not in ("missing",):
            given = err["input"]
            if not isinstance(given, dict | list):
                msg = f"{msg} (got {given!r})"
        parts.append(f"{name}: {msg}")
    return "; ".join(parts)


_TYPE_TAGS = {"float", "int", "str", "bool", "list", "dict", "none"}


def _stage_names() -> list[str]:
    from lidar_outliers.detectors import DETECTORS

    return list(DETECTORS)


def parse_pipeline_params(data: Any) -> PipelineParams:
    """Validate a pipeline document (dict or JSON text); ParameterError with one line otherwise."""
    if isinstance(data, str | bytes):
        try:
            data = json.loads(data)
        except json.JSONDecodeError as exc:
            raise ParameterError(f"parameters are not valid JSON: {exc}") from None
    if not isinstance(data, dict):
        raise ParameterError("parameters must be a JSON object")
    try:
        return PipelineParams.model_validate(data)
    except ValidationError as exc:
        raise ParameterError(validation_message(exc)) from None


