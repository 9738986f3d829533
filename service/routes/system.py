"""Landing page, health check and the problem type descriptions."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter
from fastapi.responses import JSONResponse

from lidar_outliers.jobs.storage import StorageError
from service import queue
from service.deps import ServiceDep, SettingsDep
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
def health(settings: SettingsDep, service: ServiceDep) -> JSONResponse:
    """200 when the API, the database, the file storage, Redis and at least one worker answer;
    503 naming what does not."""
    import redis

    report: dict[str, Any] = {"api": "ok"}
    try:
        service.store.count_active(0)
        report["database"] = "ok"
    except Exception as exc:  # any failure of the database is the answer
        raise Problem(503, "service-unavailable", f"the database {service.store.describe()} "
                      f"is not reachable: {exc}", **report, database="unreachable") from None
    try:
        service.storage.check()
        report["storage"] = "ok"
    except StorageError as exc:
        raise Problem(503, "service-unavailable", str(exc), **report,
                      storage="unreachable") from None
    try:
        redis.Redis.from_url(settings.redis_url, socket_timeout=2.0,
                             socket_connect_timeout=2.0).ping()
        report["redis"] = "ok"
    except Exception as exc:  # any connection failure is the answer
        raise Problem(503, "service-unavailable", f"Redis at {settings.redis_url} is not "
                      f"reachable: {exc}", **report, redis="unreachable") from None
    report["workers"] = queue.ping_workers(settings)
    if not report["workers"]:
        raise Problem(503, "service-unavailable", "no Celery worker answered; start one with "
                      "`celery -A worker.celery_app worker` (or `make run`)", **report)
    return JSONResponse({"status": "ok", **report})


@router.get("/problems/{slug}")
def problem_description(slug: str) -> dict[str, str]:
    if slug not in PROBLEMS:
        raise Problem(404, "not-found", f"no problem type {slug!r}")
    title, advice = PROBLEMS[slug]
    return {"type": f"/problems/{slug}", "title": title, "description": advice}
