"""Pipeline parameters: an ordered list of stages plus what to do with the flagged points.

The stage models come from the detector declarations (:mod:`lidar_outliers.detectors`): the
``Stage`` union below is derived from the registry, so a new detector needs no edit here. The
command line (``lidar-outliers detect``, ``lidar-outliers detectors``) and the web service
(``/processes``) validate with these models, so a parameter is spelt the same everywhere.

Every model forbids unknown fields, so a typo such as ``{"n_1": 5}`` is refused with a message that
names the field instead of being silently ignored; non-finite numbers are refused too.
"""

from __future__ import annotations

import json
from typing import Annotated, Any, Literal, Union

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from lidar_outliers.detectors import DETECTORS, FLAG_BITS, StageModel
from lidar_outliers.errors import ParameterError

__all__ = [
    "FLAG_BITS", "PipelineParams", "Stage", "default_stages", "paper_stages",
    "parse_pipeline_params", "stage", "validation_message",
]

#: One stage of a pipeline: any registered detector's model, told apart by ``detector``.
Stage = Annotated[
    Union[tuple(d.model for d in DETECTORS.values())],  # noqa: UP007
    Field(discriminator="detector"),
]


def stage(detector: str, **values: Any) -> StageModel:
    """A validated stage, e.g. ``stage("temporal", n1=5, sigma=0.01)``."""
    from lidar_outliers.detectors import get_detector

    return get_detector(detector).stage(**values)


class PipelineParams(BaseModel):
    """An ordered list of stages; a later stage sees only the points earlier stages did not flag."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    pipeline: list[Stage] | None = Field(
        None,
        description="Stages in order. Default: chosen by the sensor profile (see 'profile'); "
        "the paper's pipeline is [temporal, patch].",
    )
    profile: Literal["auto", "mobile", "spinning", "airborne", "terrestrial"] = Field(
        "auto",
        description="Sensor kind whose default pipeline runs when 'pipeline' is not given: "
        "spinning -> snow; airborne -> detached; mobile -> transient then height_field "
        "(height_field alone without gps_time); terrestrial -> height_field. 'auto' decides "
        "from the evidence a sample of the file's points carries (beam directions of pulses "
        "with several returns, platform speed, near-sensor density, scan angles, channel "
        "dimensions); ignored when 'pipeline' is given.",
    )
    classify: bool = Field(
        True, description="Write noise_class to flagged points (and 2/1 for ground)."
    )
    noise_class: int = Field(
        7, ge=0, le=255, description="ASPRS class for flagged points (7 or 18)."
    )
    reference_classes: list[Annotated[int, Field(ge=0, le=255)]] | None = Field(
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


def default_stages(has_gps_time: bool) -> list[StageModel]:
    """The mobile-mapping profile's default pipeline (:mod:`lidar_outliers.profiles`).

    ``transient`` (moving objects; it needs gps_time) then ``height_field``; ``height_field``
    alone for a file without usable gps_time.
    """
    if has_gps_time:
        return [stage("transient"), stage("height_field")]
    return [stage("height_field")]


def paper_stages(has_gps_time: bool) -> list[StageModel]:
    """The paper's pipeline (Table 5): temporal then patch; patch alone without gps_time."""
    if has_gps_time:
        return [stage("temporal"), stage("patch")]
    return [stage("patch")]


# --------------------------------------------------------------------------- validation


def validation_message(exc: ValidationError, *, option_style: bool = False) -> str:
    """One line naming the offending field(s) of a pydantic error.

    ``pipeline.0.temporal.n1`` becomes ``pipeline[0].n1`` (or ``--n1`` with ``option_style``).
    A union reports one error per member type; the field is named once, with the member's
    complaint that says most (a bound broken), else with the parameter's declared type.
    """
    by_field: dict[tuple[str, ...], list[dict[str, Any]]] = {}
    for err in exc.errors():
        by_field.setdefault(_field_location(err), []).append(err)
    parts = []
    for loc, errors in by_field.items():
        name = ".".join(f"[{item}]" if item.isdigit() else item for item in loc)
        name = name.replace(".[", "[") or "parameters"
        if option_style and loc:
            name = "--" + loc[-1].replace("_", "-")
        best = min(errors, key=_generic)
        declared = _declared_type(errors[0]) if len(errors) > 1 and _generic(best) else None
        text = _error_text(best) if declared is None else (
            f"must be {declared} (got {errors[0].get('input')!r})")
        parts.append(f"{name}: {text}")
    return "; ".join(parts)


_TYPE_TAGS = {"float", "int", "str", "bool", "list", "dict", "none"}


def _field_location(err: Any) -> tuple[str, ...]:
    """The error's field path without union member tags or the stage's detector name."""
    loc = [str(x) for x in err.get("loc", ())]
    tags = [i for i, item in enumerate(loc) if item in _TYPE_TAGS or "[" in item or "-" in item]
    if tags:  # a union member's tag: what follows lies inside that member
        loc = loc[:tags[0]]
    # The discriminated union inserts the detector name after the stage's index: drop it.
    return tuple(item for i, item in enumerate(loc)
                 if not (i > 0 and loc[i - 1].isdigit() and item in _stage_names()))


def _declared_type(err: Any) -> str | None:
    """The declared type of the stage parameter an error is about (``float | 'auto'``)."""
    from algorithms.params import parameter_infos, type_name

    loc = [str(x) for x in err.get("loc", ())]
    for i in range(1, len(loc) - 1):
        if loc[i - 1].isdigit() and loc[i] in DETECTORS:
            infos = parameter_infos(DETECTORS[loc[i]].parameters)
            found = [info for info in infos if info.name == loc[i + 1]]
            return type_name(found[0].annotation) if found else None
    return None


def _generic(err: Any) -> bool:
    """A type mismatch (says less than a broken bound when a union has both)."""
    kind = str(err.get("type", ""))
    return kind.endswith(("_type", "_parsing")) or kind in ("literal_error", "missing")


def _error_text(err: Any) -> str:
    kind = err.get("type")
    if kind == "extra_forbidden":
        return "unknown parameter"
    if kind == "union_tag_not_found":
        return f"each stage needs a \"detector\" key (one of: {', '.join(_stage_names())})"
    if kind == "union_tag_invalid":
        tag = (err.get("ctx") or {}).get("tag", err.get("input"))
        return f"unknown detector {tag!r} (known: {', '.join(_stage_names())})"
    msg = str(err.get("msg", "invalid value")).removeprefix("Value error, ")
    if "input" in err and kind != "missing" and not isinstance(err["input"], dict | list):
        msg = f"{msg} (got {err['input']!r})"
    return msg


def _stage_names() -> list[str]:
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


