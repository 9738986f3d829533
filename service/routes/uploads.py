"""/uploads: a raw request body streamed to disk, to be named by later execute requests."""

from __future__ import annotations

import os
from typing import Annotated, Literal

from fastapi import APIRouter, Query, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse

from service.deps import ServiceDep, UserDep
from service.uploads import declared_size, receive_raw, refuse_declared_size

router = APIRouter(tags=["uploads"])

UPLOAD_BODY = {
    "requestBody": {
        "required": True,
        "content": {"application/octet-stream": {"schema": {"type": "string",
                                                            "format": "binary"}}},
    }
}


@router.post("/uploads", status_code=201, openapi_extra=UPLOAD_BODY)
async def upload(
    request: Request,
    service: ServiceDep,
    user: UserDep,
    name: Annotated[str, Query(max_length=255, description="File name to remember.")] = "cloud",
    kind: Annotated[Literal["cloud", "trajectory"], Query(
        description="cloud: a LAS/LAZ file; trajectory: a text file of 'time x y z' lines "
        "for inputs.trajectory.href")] = "cloud",
) -> JSONResponse:
    """Store a LAS/LAZ file sent as the raw body (``curl --data-binary @cloud.las``), or a
    trajectory file with ``?kind=trajectory``."""
    limit, quota = await run_in_threadpool(service.upload_limit, user)
    refuse_declared_size(request.headers.get("content-length"), limit, quota, 0)
    # 507 before a byte is read when the disk cannot take the file and its result
    await run_in_threadpool(service.check_room,
                            declared_size(request.headers.get("content-length")))
    received = await receive_raw(request.stream(), service.incoming_dir, limit, quota,
                                 os.path.basename(name) or "cloud")
    assert received.path is not None
    stored = await run_in_threadpool(service.store_upload, user, received.path,
                                     received.filename, kind)
    href = f"/uploads/{stored.id}"
    return JSONResponse(
        {"id": stored.id, "href": href, "name": stored.name, "bytes": stored.bytes,
         "created": stored.created},
        status_code=201, headers={"Location": href},
    )
