"""/processes: descriptions and execution (multipart upload or JSON with an upload's href)."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse

from service.deps import ServiceDep, UserDep
from service.jobs import status_document
from service.json_body import parse_json
from service.problems import Problem
from service.processes import (
    TRAJECTORY_INPUT,
    describe,
    inputs_model,
    process_ids,
    summary,
)
from service.uploads import (
    MULTIPART_OVERHEAD,
    declared_size,
    receive_multipart,
    refuse_declared_size,
)

router = APIRouter(tags=["processes"])

MAX_JSON_BYTES = 1024**2

EXECUTE_BODY = {
    "requestBody": {
        "required": True,
        "content": {
            "multipart/form-data": {
                "schema": {
                    "type": "object",
                    "required": ["file"],
                    "properties": {
                        "file": {"type": "string", "format": "binary",
                                 "description": "The LAS or LAZ cloud."},
                        "inputs": {"type": "object",
                                   "description": "The process inputs as JSON, e.g. "
                                   '{"n1": 5}; GET /processes/{id} gives the schema.'},
                        "trajectory": {"type": "string", "format": "binary",
                                       "description": "Optional trajectory: text lines "
                                       "'time x y z' (used by the transient detector)."},
                    },
                },
                "encoding": {"inputs": {"contentType": "application/json"}},
            },
            "application/json": {
                "schema": {
                    "type": "object",
                    "required": ["inputs"],
                    "properties": {"inputs": {"type": "object", "description":
                                              'The inputs plus "cloud": {"href": '
                                              '"/uploads/<id>"} from POST /uploads and '
                                              'optionally "trajectory": {"href": ...} from '
                                              "POST /uploads?kind=trajectory."}},
                }
            },
        },
    }
}


@router.get("/processes")
def list_processes() -> dict[str, Any]:
    return {
        "processes": [summary(p) for p in process_ids()],
        "links": [{"href": "/processes", "rel": "self", "type": "application/json"}],
    }


@router.get("/processes/{process_id}")
def get_process(process_id: str) -> dict[str, Any]:
    return describe(process_id)


def _json_inputs(text: str, root: str) -> Any:
    return parse_json(text, root) if text.strip() else {}


@router.post("/processes/{process_id}/execution", status_code=201, openapi_extra=EXECUTE_BODY)
async def execute(process_id: str, request: Request, service: ServiceDep,
                  user: UserDep) -> JSONResponse:
    """Queue a job: answers 201, ``Location: /jobs/{id}`` and the status document."""
    inputs_model(process_id)  # 404 before reading a large body
    await run_in_threadpool(service.check_active_limit, user)  # 429 likewise
    content_type = request.headers.get("content-type", "")
    if content_type.startswith("multipart/form-data"):
        limit, quota = await run_in_threadpool(service.upload_limit, user)
        refuse_declared_size(request.headers.get("content-length"), limit, quota,
                             MULTIPART_OVERHEAD)
        # 507 before a byte is read when the disk cannot take the file and its result
        await run_in_threadpool(service.check_room,
                                declared_size(request.headers.get("content-length")))
        received = await receive_multipart(request.stream(), content_type,
                                           service.incoming_dir, limit, quota)
        assert received.path is not None
        try:
            inputs = _json_inputs(received.fields.get("inputs", ""), "inputs")
            params, cloud = service.parse_inputs(process_id, inputs)
            if cloud is not None:
                raise Problem(422, "invalid-parameter", "cloud: give the file in part `file` "
                              "or an href in a JSON request, not both")
        except BaseException:
            received.remove()
            raise
        job = await run_in_threadpool(service.submit, user, process_id, params, received.path,
                                      received.filename, trajectory=received.trajectory,
                                      trajectory_name=received.trajectory_name)
    elif content_type.startswith("application/json"):
        body = await request.body()
        if len(body) > MAX_JSON_BYTES:
            raise Problem(413, "file-too-large", "a JSON execute request is at most 1 MiB")
        document = _json_inputs(body.decode("utf-8", "replace"), "")
        if not isinstance(document, dict) or not isinstance(document.get("inputs", {}), dict):
            raise Problem(400, "invalid-request", 'send {"inputs": {"cloud": {"href": '
                          '"/uploads/<id>"}, ...}}')
        inputs = dict(document.get("inputs", {}))
        trajectory_ref = inputs.pop(TRAJECTORY_INPUT, None)
        params, cloud = service.parse_inputs(process_id, inputs)
        href = cloud.get("href") if isinstance(cloud, dict) else None
        if not isinstance(href, str):
            raise Problem(422, "invalid-parameter", 'cloud: missing; give "cloud": {"href": '
                          '"/uploads/<id>"} (POST /uploads first) or send multipart/form-data',
                          errors=[{"parameter": "cloud", "message": "missing href"}])
        upload = await run_in_threadpool(service.find_upload, user, href)
        trajectory = None
        if trajectory_ref is not None:
            trajectory = await run_in_threadpool(service.trajectory_upload, user, trajectory_ref)
        job = await run_in_threadpool(service.submit, user, process_id, params, upload,
                                      trajectory=trajectory)
    else:
        raise Problem(415, "unsupported-media-type",
                      "send multipart/form-data (part `file` and optional part `inputs`) or "
                      "application/json with inputs.cloud.href")
    return JSONResponse(status_document(job), status_code=201,
                        headers={"Location": f"/jobs/{job.id}"})
