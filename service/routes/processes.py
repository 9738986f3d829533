"""/processes: descriptions and execution (multipart upload or JSON with an upload's href)."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse

from lidar_outliers.jobs.documents import results_document, status_document
from lidar_outliers.jobs.store import Job, JobStatus
from service import html
from service.deps import ServiceDep, UserDep
from service.execution import Preference, subscriber_of, wait_for
from service.jobs import JobService
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

SUBSCRIBER_HELP = ("Callbacks: {\"successUri\": ..., \"failedUri\": ..., \"inProgressUri\": "
                   "...} (JSON text in a multipart request); each receives the results or "
                   "status document by POST. Private, loopback and reserved addresses are "
                   "refused unless listed in CALLBACK_ALLOW.")
PREFER = {"parameters": [{
    "name": "Prefer", "in": "header", "required": False, "schema": {"type": "string"},
    "description": "`respond-async` (the default): 201 and the status document. `wait` or "
    "`wait=<seconds>`: for a cloud of at most SYNC_MAX_POINTS points, 200 and the results "
    "document once the job is done. Preference-Applied tells which was honoured.",
}]}
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
                        "subscriber": {"type": "string", "description": SUBSCRIBER_HELP},
                    },
                },
                "encoding": {"inputs": {"contentType": "application/json"}},
            },
            "application/json": {
                "schema": {
                    "type": "object",
                    "required": ["inputs"],
                    "properties": {"subscriber": {"type": "object",
                                                  "description": SUBSCRIBER_HELP},
                                   "inputs": {"type": "object", "description":
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
def list_processes(request: Request) -> Any:
    doc = {
        "processes": [summary(p) for p in process_ids()],
        "links": [{"href": "/processes", "rel": "self", "type": "application/json",
                   "title": "this document"},
                  {"href": "/processes?f=html", "rel": "alternate", "type": "text/html",
                   "title": "this document as HTML"}],
    }
    return html.processes(doc) if html.wants_html(request) else doc


@router.get("/processes/{process_id}")
def get_process(process_id: str, request: Request) -> Any:
    doc = describe(process_id)
    return html.process(doc) if html.wants_html(request) else doc


def _json_inputs(text: str, root: str) -> Any:
    return parse_json(text, root) if text.strip() else {}


@router.post("/processes/{process_id}/execution", status_code=201,
             openapi_extra=EXECUTE_BODY | PREFER,
             responses={200: {"description": "Synchronous execution (`Prefer: wait`): the "
                              "results document."}})
async def execute(process_id: str, request: Request, service: ServiceDep,
                  user: UserDep) -> JSONResponse:
    """Queue a job: answers 201, ``Location: /jobs/{id}`` and the status document; with
    ``Prefer: wait`` and a small cloud, 200 and the results document when it is done."""
    preference = Preference.parse(request.headers.getlist("prefer"))
    base_url = str(request.base_url)
    inputs_model(process_id)  # 404 before reading a large body
    await run_in_threadpool(service.check_active_limit, user)  # 429 likewise
    content_type = request.headers.get("content-type", "")
    media_type = content_type.split(";", 1)[0].strip().lower()  # case-insensitive (RFC 9110)
    if media_type == "multipart/form-data":
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
            inputs = await run_in_threadpool(_json_inputs, received.fields.get("inputs", ""),
                                             "inputs")
            params, cloud = service.parse_inputs(process_id, inputs)
            subscriber_text = received.fields.get("subscriber", "")
            subscriber_doc = (await run_in_threadpool(_json_inputs, subscriber_text, "subscriber")
                              if subscriber_text.strip() else None)
            subscriber = await run_in_threadpool(subscriber_of, subscriber_doc,
                                                 service.settings, base_url)
            if cloud is not None:
                raise Problem(422, "invalid-parameter", "cloud: give the file in part `file` "
                              "or an href in a JSON request, not both")
        except BaseException:
            received.remove()
            raise
        job = await run_in_threadpool(service.submit, user, process_id, params, received.path,
                                      received.filename, trajectory=received.trajectory,
                                      trajectory_name=received.trajectory_name,
                                      subscriber=subscriber)
    elif media_type == "application/json":
        body = await request.body()
        if len(body) > MAX_JSON_BYTES:
            raise Problem(413, "file-too-large", "a JSON execute request is at most 1 MiB")
        document = await run_in_threadpool(_json_inputs, body.decode("utf-8", "replace"), "")
        if not isinstance(document, dict) or not isinstance(document.get("inputs", {}), dict):
            raise Problem(400, "invalid-request", 'send {"inputs": {"cloud": {"href": '
                          '"/uploads/<id>"}, ...}}')
        subscriber = await run_in_threadpool(subscriber_of, document.get("subscriber"),
                                             service.settings, base_url)
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
                                      trajectory=trajectory, subscriber=subscriber)
    else:
        raise Problem(415, "unsupported-media-type",
                      "send multipart/form-data (part `file` and optional part `inputs`) or "
                      "application/json with inputs.cloud.href")
    return await _answer(job, preference, service)


async def _answer(job: Job, preference: Preference, service: JobService) -> JSONResponse:
    """The results once done for a synchronous execution, else the status document."""
    headers = {"Location": f"/jobs/{job.id}"}
    if preference.synchronous(job, service.settings):
        done = await run_in_threadpool(wait_for, service.store, job,
                                       preference.deadline(service.settings))
        sync_headers = {"Preference-Applied": preference.applied(),
                        "Link": f'</jobs/{job.id}>; rel="monitor"'}
        if done.status is JobStatus.successful:
            return JSONResponse(results_document(done), status_code=200, headers=sync_headers)
        if done.status is JobStatus.failed:
            raise Problem(422, "job-failed", f"job {job.id} failed: {done.message}",
                          jobID=job.id, headers=sync_headers)
        job = done  # not done in time (or dismissed): answered as an asynchronous job
    elif preference.respond_async:
        headers["Preference-Applied"] = "respond-async"
    return JSONResponse(status_document(job), status_code=201, headers=headers)
