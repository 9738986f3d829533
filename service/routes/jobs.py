"""/jobs: the caller's jobs, their status, results and dismissal."""

from __future__ import annotations

from typing import Annotated, Any, Literal
from urllib.parse import urlencode

from fastapi import APIRouter, Query, Request, Response
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse

from lidar_outliers import view
from lidar_outliers.jobs.documents import MEDIA, results_document, status_document
from service import html
from service.deps import BearerDep, ServiceDep, UserDep
from service.downloads import object_response
from service.joblist import JobFilter, split_values

router = APIRouter(tags=["jobs"])

#: Largest list offset (a database integer holds more; nobody has this many jobs).
MAX_OFFSET = 10**9

#: Downloads answer HEAD too (size and validators without the body) and honour Range.
DOWNLOAD = {"methods": ["GET", "HEAD"], "response_class": Response, "responses": {
    206: {"description": "The byte range(s) asked with `Range: bytes=...`."},
    416: {"description": "Malformed or unsatisfiable `Range` (problem details)."},
}}


def _page_href(request: Request, limit: int, offset: int) -> str:
    """/jobs with the request's filters and another page."""
    query = [(k, v) for k, v in request.query_params.multi_items()
             if k not in ("limit", "offset", "f")]
    query += [("limit", str(limit)), ("offset", str(offset))]
    return f"/jobs?{urlencode(query)}"


@router.get("/jobs")
def list_jobs(
    request: Request,
    service: ServiceDep,
    user: UserDep,
    limit: Annotated[int, Query(ge=1, le=1000)] = 50,
    offset: Annotated[int, Query(ge=0, le=MAX_OFFSET)] = 0,
    process_id: Annotated[list[str], Query(alias="processID", description=
                          "Only jobs of these processes (repeat it or separate with commas).")
                          ] = [],  # noqa: B006 - FastAPI copies query defaults
    status: Annotated[list[str], Query(description="Only jobs in these states (repeat it or "
                                       "separate with commas).")] = [],  # noqa: B006
    datetime: Annotated[str | None, Query(description="Jobs created at this RFC 3339 instant "
                                          "or in this interval (start/end, '..' open).")
                        ] = None,
    min_duration: Annotated[int | None, Query(alias="minDuration", ge=0, description=
                            "Jobs that ran at least this many seconds.")] = None,
    max_duration: Annotated[int | None, Query(alias="maxDuration", ge=0, description=
                            "Jobs that ran at most this many seconds.")] = None,
    type: Annotated[list[str], Query(description="Only jobs of these types (all jobs here "
                                     "are of type `process`).")] = [],  # noqa: B006
) -> Any:
    """The caller's jobs, newest first, filtered as OGC API - Processes defines."""
    html.wants_html(request)  # 400 for an unknown f before any work
    selection = JobFilter(split_values(process_id), split_values(status), datetime,
                          min_duration, max_duration, split_values(type))
    jobs, total = selection.select(service.store, user.id, limit, offset)
    self_href = _page_href(request, limit, offset)
    links = [{"href": self_href, "rel": "self", "type": "application/json"},
             {"href": self_href + "&f=html", "rel": "alternate", "type": "text/html"}]
    if offset + len(jobs) < total:
        links.append({"href": _page_href(request, limit, offset + limit), "rel": "next",
                      "type": "application/json"})
    if offset > 0:
        links.append({"href": _page_href(request, limit, max(0, offset - limit)),
                      "rel": "prev", "type": "application/json"})
    doc = {"jobs": [status_document(j) for j in jobs], "numberMatched": total,
           "numberReturned": len(jobs), "links": links}
    return html.jobs(doc, self_href) if html.wants_html(request) else doc


@router.get("/jobs/{job_id}")
async def get_job(job_id: str, request: Request, service: ServiceDep,
                  _key: BearerDep) -> Response:
    """The job's status document (what clients poll: one database query, one thread hop), or
    its HTML page for a browser."""
    wants_html = html.wants_html(request)
    job = await run_in_threadpool(service.poll, request.headers.get("authorization"), job_id)
    doc = status_document(job)
    return html.job(doc) if wants_html else JSONResponse(doc)


@router.delete("/jobs/{job_id}")
def dismiss_job(job_id: str, service: ServiceDep, user: UserDep) -> dict[str, Any]:
    """Cancel a queued or running job, or delete a finished job's files; answers the status
    document with status ``dismissed``."""
    return status_document(service.dismiss(user, job_id))


@router.get("/jobs/{job_id}/results")
def get_results(job_id: str, service: ServiceDep, user: UserDep) -> dict[str, Any]:
    job, _, _ = service.result(user, job_id, "cloud")
    return results_document(job)


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
