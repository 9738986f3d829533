"""The OpenAPI document as the API really answers: every error status of every operation, as
``application/problem+json`` (RFC 9457), and one operation id per method.

FastAPI documents the success answer and a JSON 422 of its own shape; the routes raise
:class:`service.problems.Problem` for everything else. The statuses below are those the service
logic raises, per operation, plus the ones every operation of a kind can answer.
"""

from __future__ import annotations

import warnings
from typing import Any

from fastapi import FastAPI
from fastapi.openapi.utils import get_openapi

from service.problems import MEDIA_TYPE, PROBLEMS
from service.processes import process_ids

PROBLEM_SCHEMA: dict[str, Any] = {
    "type": "object",
    "description": "RFC 9457 problem details.",
    "required": ["type", "title", "status", "detail"],
    "properties": {
        "type": {"type": "string", "description": "URI of the problem type; relative ones "
                 "(/problems/<slug>) are served by the API."},
        "title": {"type": "string"},
        "status": {"type": "integer"},
        "detail": {"type": "string", "description": "What was wrong with this request."},
        "errors": {"type": "array", "items": {"type": "object"},
                   "description": "Each wrong parameter and why."},
    },
    "additionalProperties": True,
}

DESCRIPTIONS = {
    400: "Malformed request: body, multipart parts, JSON nesting, or an empty file.",
    401: "Missing, wrong or revoked API key.",
    404: "No such process, job, upload result or problem type (of yours).",
    413: "File larger than MAX_UPLOAD_BYTES, or over the storage quota.",
    415: "Not a LAS/LAZ file, or a request body of another type.",
    416: "Malformed or unsatisfiable `Range`.",
    422: "Invalid parameter: the problem's `errors` name each one.",
    429: "Too many queued or running jobs (see `Retry-After`).",
    409: "Resumable upload: `Upload-Offset` is not the upload's offset (ask with HEAD).",
    410: "Resumable upload: expired (start a new one).",
    412: "Resumable upload: the request does not speak tus 1.0.0 (`Tus-Resumable`).",
    423: "Resumable upload: another request is writing to it; retry.",
    460: "Resumable upload: `Upload-Checksum` does not match the piece (offset unchanged).",
    503: "Redis, the workers, the database or the file storage are not reachable.",
    507: "The server's disk is full (or would be, with this file and its result).",
}

#: Statuses of the operations that receive a file (besides 401 and 422).
RECEIVING = (400, 404, 413, 415, 429, 503, 507)
#: (method, path) -> the statuses that operation answers besides 401, 404 and 422 that every
#: operation with a key, a path parameter or a query answers.
OPERATIONS: dict[tuple[str, str], tuple[int, ...]] = {
    ("post", "/processes/{process_id}/execution"): RECEIVING,
    ("post", "/uploads"): (400, 413, 415, 503, 507),
    ("get", "/health"): (503,),
    ("delete", "/jobs/{job_id}"): (503,),
    ("get", "/jobs/{job_id}/results"): (404, 503),
    ("get", "/jobs/{job_id}/results/points"): (404, 503, 507),
    ("get", "/jobs"): (400,),
    # resumable uploads (tus 1.0.0)
    ("post", "/uploads/tus"): (400, 412, 413, 503, 507),
    ("head", "/uploads/tus/{upload_id}"): (410, 412),
    ("patch", "/uploads/tus/{upload_id}"): (400, 409, 410, 412, 413, 415, 423, 460, 503, 507),
    ("delete", "/uploads/tus/{upload_id}"): (410, 412, 423),
}
#: Headers the tus protocol requires, as their schemas: the values the server accepts.
TUS_HEADERS: dict[str, dict[str, Any]] = {
    "tus-resumable": {"type": "string", "enum": ["1.0.0"]},
    "upload-length": {"type": "string", "pattern": "^[1-9][0-9]{0,18}$"},  # a file: > 0
    "upload-offset": {"type": "string", "pattern": "^[0-9]{1,19}$"},
}
DOWNLOADS = ("/jobs/{job_id}/results/cloud", "/jobs/{job_id}/results/statistics",
             "/jobs/{job_id}/results/preview")
for _path in DOWNLOADS:
    for _method in ("get", "head"):
        OPERATIONS[(_method, _path)] = (404, 416, 503, 507)


def _problem(status: int) -> dict[str, Any]:
    return {"description": DESCRIPTIONS[status], "content": {
        MEDIA_TYPE: {"schema": {"$ref": "#/components/schemas/Problem"}}}}


def _statuses(method: str, path: str, operation: dict[str, Any]) -> set[int]:
    statuses = set(OPERATIONS.get((method, path), ()))
    if operation.get("security") or path == "/health":
        statuses.add(401)
    if "{" in path:
        statuses.add(404)
    if operation.get("parameters") or operation.get("requestBody"):
        statuses.add(422)
    return statuses


def _name_the_values(operation: dict[str, Any]) -> None:
    """Path parameters that take one of a known list get it as their enum."""
    known = {"process_id": process_ids(), "slug": sorted(PROBLEMS)}
    for parameter in operation.get("parameters", []):
        if parameter.get("in") == "path" and parameter["name"] in known:
            parameter["schema"]["enum"] = known[parameter["name"]]


def _require_tus_headers(path: str, operation: dict[str, Any]) -> None:
    """The tus headers a resumable-upload request must send: required, with the accepted values
    (FastAPI sees optional strings, since the routes answer their absence with tus statuses)."""
    if not path.startswith("/uploads/tus"):
        return
    for parameter in operation.get("parameters", []):
        wanted = (TUS_HEADERS.get(parameter["name"].lower())
                  if parameter.get("in") == "header" else None)
        if wanted is not None:
            parameter["required"] = True
            parameter["schema"] = dict(wanted)


def document(app: FastAPI) -> dict[str, Any]:
    """The app's OpenAPI document, made once."""
    if app.openapi_schema:
        return app.openapi_schema
    with warnings.catch_warnings():  # GET and HEAD of one route share an id; renamed below
        warnings.simplefilter("ignore")
        schema = get_openapi(title=app.title, version=app.version,
                             description=app.description, routes=app.routes)
    schema.setdefault("components", {}).setdefault("schemas", {})["Problem"] = PROBLEM_SCHEMA
    for path, operations in schema["paths"].items():
        for method, operation in operations.items():
            _name_the_values(operation)
            _require_tus_headers(path, operation)
            if method == "head":
                operation["operationId"] = operation["operationId"].removesuffix("_get") + "_head"
            responses = operation.setdefault("responses", {})
            for status in sorted(_statuses(method, path, operation)):
                responses[str(status)] = _problem(status)
    for name in ("HTTPValidationError", "ValidationError"):
        schema["components"]["schemas"].pop(name, None)
    app.openapi_schema = schema
    return schema
