"""The FastAPI application: routers, problem-details error handlers, periodic retention cleanup.

Run it with ``uvicorn --factory service.app:create_app`` (``lidar-outliers serve`` does).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from fastapi.routing import APIRoute
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match

from lidar_outliers.jobs.diskspace import is_disk_full
from lidar_outliers.jobs.settings import Settings, get_settings
from lidar_outliers.jobs.store import Store
from service import openapi
from service.cors import CORSMiddleware
from service.headers import SecurityHeaders
from service.health import HealthMonitor
from service.jobs import JobService
from service.problems import MEDIA_TYPE, Problem, insufficient_storage
from service.routes import docs, jobs, pages, processes, system, tus, uploads
from service.tus import ResumableUploads

log = logging.getLogger(__name__)


def problem_response(problem: Problem) -> JSONResponse:
    return JSONResponse(problem.body(), status_code=problem.status, headers=problem.headers,
                        media_type=MEDIA_TYPE)


async def _on_problem(_: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, Problem)
    return problem_response(exc)


async def _on_validation(_: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, RequestValidationError)
    errors = [
        {"parameter": ".".join(str(p) for p in e["loc"][1:] or e["loc"]), "in": e["loc"][0],
         "message": e["msg"]}
        for e in exc.errors()
    ]
    detail = "; ".join(f"{e['parameter']} ({e['in']}): {e['message']}" for e in errors)
    return problem_response(Problem(422, "invalid-parameter", detail, errors=errors))


def _allowed_methods(request: Request) -> list[str]:
    """Methods of every route of this path (Starlette's 405 names those of one route only)."""
    methods: set[str] = set()
    for route in request.app.state.api_routes:
        if isinstance(route, APIRoute) and route.matches(request.scope)[0] is not Match.NONE:
            methods |= route.methods or set()
    return sorted(methods)


async def _on_http(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, StarletteHTTPException)
    slug = {404: "not-found", 405: "method-not-allowed"}.get(exc.status_code, "invalid-request")
    detail = str(exc.detail)
    headers = dict(exc.headers or {})
    if exc.status_code == 404:
        detail = "no such route; GET /docs lists the routes"
    elif exc.status_code == 405:
        allowed = _allowed_methods(request)
        if allowed:
            headers["Allow"] = ", ".join(allowed)
            detail = f"{request.method} is not allowed here; allowed: {headers['Allow']}"
    return problem_response(Problem(exc.status_code, slug, detail, headers=headers))


def _on_crash(settings: Settings):
    async def handler(request: Request, exc: Exception) -> JSONResponse:
        if is_disk_full(exc):  # e.g. the database could not grow: nothing was committed
            log.warning("disk full on %s %s: %s", request.method, request.url.path, exc)
            return problem_response(insufficient_storage(exc))
        log.exception("unhandled error on %s %s", request.method, request.url.path)
        detail = "internal error" if settings.environment == "prod" else (
            f"internal error: {type(exc).__name__}: {exc}")
        return problem_response(Problem(500, "internal-error", detail))

    return handler


async def _check_health_forever(monitor: HealthMonitor) -> None:
    """Keep /health's report fresh so that requests do not wait for a worker ping."""
    while True:
        try:
            await asyncio.to_thread(monitor.refresh)
        except Exception:
            log.exception("health check failed")
        await asyncio.sleep(monitor.interval)


async def _cleanup_forever(service: JobService) -> None:
    while True:
        try:
            removed = await asyncio.to_thread(service.cleanup)
            if removed:
                log.info("retention: removed %d jobs/uploads", removed)
        except Exception:
            log.exception("retention cleanup failed")
        await asyncio.sleep(service.settings.cleanup_interval_seconds)


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or get_settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        tasks = [asyncio.create_task(_cleanup_forever(app.state.service)),
                 asyncio.create_task(_check_health_forever(app.state.health))]
        yield
        for task in tasks:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task

    app = FastAPI(
        title="lidar-outliers",
        version="0.1.0",
        description="Outlier detection for mobile LiDAR point clouds as OGC API - Processes "
        "jobs. Authenticate with `Authorization: Bearer <key>`.",
        lifespan=lifespan,
        docs_url=None,  # served from installed files by service.routes.docs
        redoc_url=None,
    )
    app.openapi = lambda: openapi.document(app)  # type: ignore[method-assign]
    app.add_middleware(SecurityHeaders)
    app.state.settings = settings
    # opening the store migrates the database's schema (safely when several APIs start at once)
    service = JobService(settings, Store(settings.database_url))
    app.state.service = service
    app.state.health = HealthMonitor(settings, service.store, service.storage)
    app.state.resumable = ResumableUploads(service)
    app.add_exception_handler(Problem, _on_problem)
    app.add_exception_handler(RequestValidationError, _on_validation)
    app.add_exception_handler(StarletteHTTPException, _on_http)
    app.add_exception_handler(Exception, _on_crash(settings))
    modules = (system, processes, tus, uploads, jobs, pages, docs)
    for module in modules:
        app.include_router(module.router)
    app.state.api_routes = [route for module in modules for route in module.router.routes]
    app.mount("/app/static", pages.static_files(), name="app-static")
    app.mount(docs.ASSETS_URL, docs.static_files(), name="docs-static")
    if settings.cors_origin_list:
        app.add_middleware(CORSMiddleware, origins=settings.cors_origin_list)
    return app
