"""Process descriptions (OGC API - Processes) and input validation, generated from the detector
declarations (:mod:`lidar_outliers.detectors`) so the API, the CLI and the worker share one
contract.

A single-detector process takes that detector's parameters plus the pipeline-level fields
(``classify``, ``noise_class``, ``reference_classes``); the ``pipeline`` process takes
:class:`lidar_outliers.params.PipelineParams` as it is.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Any

from pydantic import BaseModel, ConfigDict, ValidationError, create_model

from lidar_outliers.detectors import DETECTORS
from lidar_outliers.params import PipelineParams
from service.oas30 import process_input_schema
from service.problems import Problem

PIPELINE = "pipeline"
PIPELINE_LEVEL = ("classify", "noise_class", "reference_classes")
#: The input that names the cloud in a JSON execute request; not a parameter.
CLOUD_INPUT = "cloud"
#: Every process runs asynchronously (the default), synchronously with ``Prefer: wait`` for
#: clouds up to SYNC_MAX_POINTS, and its jobs can be dismissed.
JOB_CONTROL_OPTIONS = ["sync-execute", "async-execute", "dismiss"]
#: The optional trajectory file (multipart part of this name); not a parameter.
TRAJECTORY_INPUT = "trajectory"


def stage_models() -> dict[str, type[BaseModel]]:
    """Each registered detector's stage model, by name."""
    return {name: detector.model for name, detector in DETECTORS.items()}


def process_ids() -> list[str]:
    return [*stage_models(), PIPELINE]


@lru_cache
def inputs_model(process_id: str) -> type[BaseModel]:
    """The pydantic model of one process's inputs (raises Problem 404 for an unknown id)."""
    if process_id == PIPELINE:
        return PipelineParams
    models = stage_models()
    if process_id not in models:
        raise Problem(404, "no-such-process", f"no process {process_id!r}; choose one of "
                      f"{', '.join(process_ids())}")
    stage = models[process_id]
    fields: dict[str, Any] = {
        name: (info.annotation, info)
        for name, info in stage.model_fields.items()
        if name != "detector"
    }
    for name in PIPELINE_LEVEL:
        info = PipelineParams.model_fields[name]
        fields[name] = (info.annotation, info)
    model = create_model(
        f"{stage.__name__.removesuffix('Params')}Inputs",
        __config__=ConfigDict(extra="forbid", allow_inf_nan=False),
        __doc__=stage.__doc__,
        **fields,
    )
    # keep the stage's own validators (e.g. sigma > 0 or 'auto') by validating through it too
    model.__stage_model__ = stage  # type: ignore[attr-defined]
    return model


def resolve_inputs(process_id: str, inputs: dict[str, Any]) -> PipelineParams:
    """Validate a request's inputs into the pipeline the worker runs.

    Raises Problem 422 naming each wrong parameter."""
    model = inputs_model(process_id)
    try:
        if process_id == PIPELINE:
            return PipelineParams.model_validate(inputs)
        checked = model.model_validate(inputs)
        stage_fields = {
            k: v for k, v in checked.model_dump().items() if k not in PIPELINE_LEVEL
        }
        stage = model.__stage_model__.model_validate(  # type: ignore[attr-defined]
            {"detector": process_id, **stage_fields}
        )
        return PipelineParams(
            pipeline=[stage],
            **{k: getattr(checked, k) for k in PIPELINE_LEVEL},
        )
    except ValidationError as exc:
        raise invalid_inputs(exc) from None


def invalid_inputs(exc: ValidationError) -> Problem:
    errors = [
        {"parameter": ".".join(str(p) for p in e["loc"]) or "inputs", "message": e["msg"]}
        for e in exc.errors()
    ]
    detail = "; ".join(f"{e['parameter']}: {e['message']}" for e in errors)
    return Problem(422, "invalid-parameter", detail, errors=errors)


def _schema_of(model: type[BaseModel]) -> dict[str, Any]:
    return model.model_json_schema()


def describe(process_id: str, base_url: str = "") -> dict[str, Any]:
    """OGC process description: inputs as JSON Schema with their defaults."""
    model = inputs_model(process_id)
    schema = _schema_of(model)
    defs = schema.get("$defs", {})
    inputs: dict[str, Any] = {
        CLOUD_INPUT: {
            "title": "Point cloud",
            "description": "LAS 1.0-1.4 or LAZ: multipart part `file`, or "
            "{\"href\": \"/uploads/<id>\"} from POST /uploads in a JSON execute request.",
            "minOccurs": 1,
            "maxOccurs": 1,
            "schema": {"type": "string", "contentMediaType": "application/vnd.laszip",
                       "contentEncoding": "binary"},
        }
    }
    inputs[TRAJECTORY_INPUT] = {
        "title": "Trajectory",
        "description": "Optional: the platform's path as text lines 'time x y z' (same time base "
        "and coordinates as the cloud; `lidar-outliers simulate` writes one) in multipart part "
        "`trajectory` beside `file`. The transient detector then also flags points other beams "
        "saw through (see its lever_arms).",
        "minOccurs": 0,
        "maxOccurs": 1,
        "schema": {"type": "string", "contentMediaType": "text/plain"},
    }
    for name, prop in schema.get("properties", {}).items():
        prop = process_input_schema(prop, defs)
        inputs[name] = {
            "title": prop.get("title", name),
            "description": prop.pop("description", ""),
            "minOccurs": 0,
            "maxOccurs": 1,
            "schema": prop,
        }
    doc = (model.__doc__ or "").strip()
    if process_id == PIPELINE:
        title = "Pipeline of detectors"
    else:
        title = f"{process_id} detector"
    return {
        "id": process_id,
        "title": title,
        "description": doc,
        "version": "0.1.0",
        "jobControlOptions": JOB_CONTROL_OPTIONS,
        "outputTransmission": ["reference"],
        "inputs": inputs,
        "outputs": {
            "cloud": {
                "title": "Flagged point cloud",
                "description": "The input with outlier_flags and <detector>_score extra "
                "dimensions (and noise classes when classify is on).",
                "schema": {"type": "string", "contentMediaType": "application/vnd.las",
                           "contentEncoding": "binary"},
            },
            "statistics": {
                "title": "Statistics",
                "description": "Per stage: points tested and flagged, resolved parameters, "
                "seconds; confusion counts with reference_classes.",
                "schema": {"type": "object", "contentMediaType": "application/json"},
            },
        },
        "links": [
            {"href": f"{base_url}/processes/{process_id}", "rel": "self",
             "type": "application/json", "title": "this document"},
            {"href": f"{base_url}/processes/{process_id}?f=html", "rel": "alternate",
             "type": "text/html", "title": "this document as HTML"},
            {"href": f"{base_url}/processes/{process_id}/execution", "rel":
             "http://www.opengis.net/def/rel/ogc/1.0/execute", "title": "Execute"},
        ],
    }


def summary(process_id: str, base_url: str = "") -> dict[str, Any]:
    full = describe(process_id, base_url)
    return {
        k: full[k] for k in ("id", "title", "description", "version", "jobControlOptions",
                             "outputTransmission")
    } | {
        "links": [{"href": f"{base_url}/processes/{process_id}", "rel": "self",
                   "type": "application/json", "title": "process description"}]
    }


def preflight(params: PipelineParams, point_format: int, has_gps_time: bool = True) -> None:
    """Refuse before queueing what the worker would refuse at once: a detector twice in a
    pipeline, a noise class the point format cannot hold, a stage that needs gps_time on a
    point format without it."""
    from lidar_outliers.detectors import get_detector
    from lidar_outliers.errors import ParameterError
    from lidar_outliers.pipeline import check_noise_class, resolve_stages

    try:
        resolve_stages(params, None)
        check_noise_class(params, point_format)
        for stage in params.pipeline or []:
            if "gps_time" in get_detector(stage.detector).needs and not has_gps_time:
                raise ParameterError(
                    f"the {stage.detector} detector needs gps_time, which point format "
                    f"{point_format} does not have (use point format 1, 3-10, or another "
                    "detector)")
    except ParameterError as exc:
        raise Problem(422, "invalid-parameter", str(exc),
                      errors=[{"parameter": "inputs", "message": str(exc)}]) from None
