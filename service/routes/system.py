"""Landing page, health check and the problem type descriptions."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Request
from fastapi.responses import JSONResponse

from service import html
from service.deps import ServiceDep
from service.oas30 import openapi_30
from service.problems import PROBLEMS, Problem

router = APIRouter(tags=["system"])


OGC_REL = "http://www.opengis.net/def/rel/ogc/1.0/"
CONFORMANCE = "http://www.opengis.net/spec/ogcapi-processes-1/1.0/conf/"
#: Every class of Part 1, each implemented (tests/e2e/test_ogc.py checks each).
CONFORMANCE_CLASSES = ["core", "ogc-process-description", "json", "html", "oas30", "job-list",
                       "callback", "dismiss"]
OPENAPI_30 = "application/vnd.oai.openapi+json;version=3.0"


@router.get("/")
def landing(request: Request) -> Any:
    """The landing page: links to the API definition, the conformance declaration, the
    processes and the jobs."""
    doc = {
        "title": "lidar-outliers",
        "description": "Outlier detection for mobile LiDAR point clouds (OGC API - Processes).",
        "links": [
            {"href": "/", "rel": "self", "type": "application/json", "title": "this document"},
            {"href": "/?f=html", "rel": "alternate", "type": "text/html",
             "title": "this document as HTML"},
            {"href": "/api", "rel": "service-desc", "type": OPENAPI_30,
             "title": "the API definition (OpenAPI 3.0)"},
            {"href": "/docs", "rel": "service-doc", "type": "text/html",
             "title": "the API documentation"},
            {"href": "/conformance", "rel": OGC_REL + "conformance", "type": "application/json",
             "title": "conformance classes implemented"},
            {"href": "/processes", "rel": OGC_REL + "processes", "type": "application/json",
             "title": "the processes"},
            {"href": "/jobs", "rel": OGC_REL + "job-list", "type": "application/json",
             "title": "your jobs"},
            {"href": "/health", "rel": "status", "type": "application/json",
             "title": "health of the service"},
            {"href": "/app", "rel": "alternate", "type": "text/html",
             "title": "job page: upload, follow and view jobs in a browser"},
        ],
    }
    return html.landing(doc) if html.wants_html(request) else doc


@router.get("/conformance")
def conformance(request: Request) -> Any:
    doc = {"conformsTo": [CONFORMANCE + name for name in CONFORMANCE_CLASSES]}
    return html.conformance(doc) if html.wants_html(request) else doc


@router.get("/api", response_class=JSONResponse,
            responses={200: {"content": {OPENAPI_30: {}}}})
def api_definition(request: Request) -> JSONResponse:
    """This API's definition as OpenAPI 3.0 (``/openapi.json`` has the same in OpenAPI 3.1)."""
    app = request.app
    if getattr(app.state, "openapi_30", None) is None:
        app.state.openapi_30 = openapi_30(app.openapi())
    return JSONResponse(app.state.openapi_30, media_type=OPENAPI_30)


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
