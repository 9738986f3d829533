"""Landing page, health check and the problem type descriptions."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Request
from fastapi.responses import JSONResponse

from service.deps import ServiceDep
from service.problems import PROBLEMS, Problem

router = APIRouter(tags=["system"])


@router.get("/")
def landing() -> dict[str, Any]:
    return {
        "title": "lidar-outliers",
        "description": "Outlier detection for mobile LiDAR point clouds (OGC API - Processes).",
        "links": [
            {"href": "/processes", "rel": "http://www.opengis.net/def/rel/ogc/1.0/processes"},
            {"href": "/jobs", "rel": "http://www.opengis.net/def/rel/ogc/1.0/job-list"},
            {"href": "/docs", "rel": "service-doc", "type": "text/html"},
            {"href": "/openapi.json", "rel": "service-desc",
             "type": "application/vnd.oai.openapi+json;version=3.0"},
            {"href": "/health", "rel": "status"},
            {"href": "/app", "rel": "alternate", "type": "text/html",
             "title": "job page: upload, follow and view jobs in a browser"},
        ],
    }


@router.get("/conformance")
def conformance() -> dict[str, Any]:
    return {"conformsTo": [
        "http://www.opengis.net/spec/ogcapi-processes-1/1.0/conf/core",
        "http://www.opengis.net/spec/ogcapi-processes-1/1.0/conf/json",
        "http://www.opengis.net/spec/ogcapi-processes-1/1.0/conf/job-list",
        "http://www.opengis.net/spec/ogcapi-processes-1/1.0/conf/dismiss",
    ]}


@router.get("/health")
def health(request: Request, service: ServiceDep) -> JSONResponse:
    """200 when the API, the database, the file storage, Redis and at least one worker answer;
    503 naming what does not. Checked every few seconds, not on each request. Without a key it
    gives component states only; with a key, worker names and what failed where."""
    detailed = "authorization" in request.headers
    if detailed:
        service.authenticate(request.headers["authorization"])  # 401 for a wrong key
    report = request.app.state.health.report()
    body = report.body(detailed)
    if not report.ok:
        raise Problem(503, "service-unavailable",
                      report.detail if detailed else report.public_detail, **body)
    return JSONResponse({"status": "ok", **body})


@router.get("/problems/{slug}")
def problem_description(slug: str) -> dict[str, str]:
    if slug not in PROBLEMS:
        raise Problem(404, "not-found", f"no problem type {slug!r}")
    title, advice = PROBLEMS[slug]
    return {"type": f"/problems/{slug}", "title": title, "description": advice}
