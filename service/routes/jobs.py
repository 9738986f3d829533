"""/jobs: the caller's jobs, their status, results and dismissal."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from fastapi import APIRouter, Query, Request, Response
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse

from lidar_outliers import view
from service.deps import BearerDep, ServiceDep, UserDep
from service.downloads import object_response
from service.jobs import status_document

router = APIRouter(tags=["jobs"])

#: Largest list offset (a database integer holds more; nobody has this many jobs).
MAX_OFFSET = 10**9

MEDIA = {".las": "application/vnd.las", ".laz": "application/vnd.laszip"}
#: Downloads answer HEAD too (size and validators without the body) and honour Range.
DOWNLOAD = {"methods": ["GET", "HEAD"], "response_class": Response, "responses": {
    206: {"description": "The byte range(s) asked with `Range: bytes=...`."},
    416: {"description": "Malformed or unsatisfiable `Range` (problem details)."},
}}


@router.get("/jobs")
def list_jobs(
    service: ServiceDep,
    user: UserDep,
    limit: Annotated[int, Query(ge=1, le=1000)] = 50,
    offset: Annotated[int, Query(ge=0, le=MAX_OFFSET)] = 0,
) -> dict[str, Any]:
    """The caller's jobs, newest first."""
    jobs, total = service.list_jobs(user, limit, offset)
    links = [{"href": f"/jobs?limit={limit}&offset={offset}", "rel": "self",
              "type": "application/json"}]
    if offset + len(jobs) < total:
        links.append({"href": f"/jobs?limit={limit}&offset={offset + limit}", "rel": "next",
                      "type": "application/json"})
    if offset > 0:
        links.append({"href": f"/jobs?limit={limit}&offset={max(0, offset - limit)}",
                      "rel": "prev", "type": "application/json"})
    return {"jobs": [status_document(j) for j in jobs], "numberMatched": total,
            "numberReturned": len(jobs), "links": links}


@router.get("/jobs/{job_id}")
async def get_job(job_id: str, request: Request, service: ServiceDep,
                  _key: BearerDep) -> JSONResponse:
    """The job's status document (what clients poll: one database query, one thread hop)."""
    job = await run_in_threadpool(service.poll, request.headers.get("authorization"), job_id)
    return JSONResponse(status_document(job))


@router.delete("/jobs/{job_id}")
def dismiss_job(job_id: str, service: ServiceDep, user: UserDep) -> dict[str, Any]:
    """Cancel a queued or running job, or delete a finished job's files."""
    return status_document(service.dismiss(user, job_id))


@router.get("/jobs/{job_id}/results")
def get_results(job_id: str, service: ServiceDep, user: UserDep) -> dict[str, Any]:
    job, _, _ = service.result(user, job_id, "cloud")
    base = f"/jobs/{job_id}/results"
    cloud_type = MEDIA[".laz" if job.laz else ".las"]
    return {
        "cloud": {"href": f"{base}/cloud", "type": cloud_type,
                  "title": "flagged cloud (?keep=inliers|outliers, ?format=las|laz)"},
        "statistics": {"href": f"{base}/statistics", "type": "application/json"},
        "preview": {"href": f"{base}/preview", "type": "image/png"},
        "points": {"href": f"{base}/points", "type": view.MEDIA_TYPE,
                   "title": "decimated points for a viewer (?max_points=N)"},
    }


@router.api_route("/jobs/{job_id}/results/cloud", **DOWNLOAD)
def get_cloud(
    job_id: str,
    request: Request,
    service: ServiceDep,
    user: UserDep,
    keep: Literal["all", "inliers", "outliers"] = "all",
    format: Literal["las", "laz"] | None = None,
) -> Response:
    """The flagged cloud; LAZ when the input was LAZ or with ``?format=laz``."""
    laz = None if format is None else format == "laz"
    key, info, laz = service.cloud(user, job_id, keep, laz)
    suffix = ".laz" if laz else ".las"
    keep_part = f"-{keep}" if keep != "all" else ""
    return object_response(request, service.storage, key, info, MEDIA[suffix],
                           filename=f"{job_id}{keep_part}{suffix}")


@router.api_route("/jobs/{job_id}/results/statistics", **DOWNLOAD)
def get_statistics(job_id: str, request: Request, service: ServiceDep,
                   user: UserDep) -> Response:
    _, key, info = service.result(user, job_id, "statistics")
    return object_response(request, service.storage, key, info, "application/json")


@router.api_route("/jobs/{job_id}/results/preview", **DOWNLOAD)
def get_preview(job_id: str, request: Request, service: ServiceDep, user: UserDep) -> Response:
    """A PNG of the flagged cloud, rendered on first request."""
    key, info = service.preview(user, job_id)
    return object_response(request, service.storage, key, info, "image/png")


@router.get("/jobs/{job_id}/results/points", response_class=Response,
            responses={200: {"content": {view.MEDIA_TYPE: {}}}})
def get_points(
    job_id: str,
    request: Request,
    service: ServiceDep,
    user: UserDep,
    max_points: Annotated[int, Query(ge=1, le=5_000_000)] = view.DEFAULT_MAX_POINTS,
) -> Response:
    """At most ``max_points`` points of the flagged cloud for a viewer, spread evenly in space
    with every flagged point kept: float32 xyz about a centre and the uint16 outlier_flags after
    a JSON header (layout in ``lidar_outliers/view.py``)."""
    if max_points == view.DEFAULT_MAX_POINTS:  # what the page asks for: made once, kept
        key, info = service.view_points(user, job_id)
        return object_response(request, service.storage, key, info, view.MEDIA_TYPE)
    return Response(service.view_points_bytes(user, job_id, max_points),
                    media_type=view.MEDIA_TYPE)
