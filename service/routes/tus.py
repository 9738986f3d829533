"""/uploads/tus: resumable uploads with the tus protocol 1.0.0 (:mod:`service.tus`).

``OPTIONS /uploads/tus`` says what the server offers (no key needed); the other requests carry
the API key and ``Tus-Resumable: 1.0.0``. A finished upload is ``/uploads/<id>`` for jobs.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Header, Request, Response
from fastapi.responses import JSONResponse

from service.deps import UserDep
from service.tus import (
    CONTENT_TYPE,
    ResumableUploads,
    check_version,
    http_date,
    parse_checksum,
    parse_length,
    parse_metadata,
    problem,
    tus_headers,
)

router = APIRouter(tags=["uploads"])


def get_uploads(request: Request) -> ResumableUploads:
    return request.app.state.resumable


UploadsDep = Annotated[ResumableUploads, Depends(get_uploads)]
#: Every request but OPTIONS names the protocol version.
TusHeader = Annotated[str | None, Header(alias="Tus-Resumable")]
PATCH_BODY = {"requestBody": {"required": True, "content": {
    CONTENT_TYPE: {"schema": {"type": "string", "format": "binary"}}}}}


@router.options("/uploads/tus", status_code=204)
def discover(uploads: UploadsDep) -> Response:
    """The protocol versions, extensions, largest size and checksum algorithms offered."""
    return Response(status_code=204, headers=uploads.options_headers())


@router.post("/uploads/tus", status_code=201)
def create(
    uploads: UploadsDep,
    user: UserDep,
    tus_resumable: TusHeader = None,
    upload_length: Annotated[str | None, Header()] = None,
    upload_metadata: Annotated[str | None, Header()] = None,
) -> JSONResponse:
    """Create an upload of ``Upload-Length`` bytes (reserved against your quota);
    ``Upload-Metadata`` may give ``filename`` and ``kind`` (cloud or trajectory). 201 with
    ``Location``: the URL to PATCH."""
    check_version(tus_resumable)
    if upload_length is None:
        raise problem(400, "invalid-request", "Upload-Length is required (deferred lengths "
                      "are not supported)")
    created = uploads.create(user, parse_length(upload_length, "Upload-Length"),
                             parse_metadata(upload_metadata))
    location = f"/uploads/tus/{created.id}"
    return JSONResponse(
        {"id": created.id, "location": location, "href": f"/uploads/{created.id}",
         "name": created.name, "length": created.length, "expires": created.expires},
        status_code=201,
        headers=tus_headers(Location=location, **{"Upload-Expires": http_date(created.expires),
                                                  "Upload-Offset": "0"}))


@router.head("/uploads/tus/{upload_id}")
def offset(upload_id: str, uploads: UploadsDep, user: UserDep,
           tus_resumable: TusHeader = None) -> Response:
    """``Upload-Offset``: where to continue; ``Upload-Length``; ``Upload-Expires``."""
    check_version(tus_resumable)
    return Response(status_code=200, headers=uploads.head_headers(uploads.find(user, upload_id)))


@router.patch("/uploads/tus/{upload_id}", status_code=204, openapi_extra=PATCH_BODY)
async def append(
    upload_id: str,
    request: Request,
    uploads: UploadsDep,
    user: UserDep,
    tus_resumable: TusHeader = None,
    upload_offset: Annotated[str | None, Header()] = None,
    upload_checksum: Annotated[str | None, Header()] = None,
    content_type: Annotated[str | None, Header()] = None,
    content_length: Annotated[str | None, Header()] = None,
) -> Response:
    """Append the body at ``Upload-Offset`` (409 when it is not the upload's offset); with
    ``Upload-Checksum: sha1 <base64>`` (or sha256, md5) a body that differs is dropped (460).
    204 with the new ``Upload-Offset``; after the last byte, ``Upload-Href`` names the upload
    for jobs."""
    check_version(tus_resumable)
    if (content_type or "").split(";")[0].strip().lower() != CONTENT_TYPE:
        raise problem(415, "wrong-content-type", f"Content-Type must be {CONTENT_TYPE}")
    start = parse_length(upload_offset, "Upload-Offset")
    length = parse_length(content_length, "Content-Length") if content_length else None
    headers = await uploads.patch(user, upload_id, start, length,
                                  parse_checksum(upload_checksum), request.stream())
    return Response(status_code=204, headers=headers)


@router.delete("/uploads/tus/{upload_id}", status_code=204)
def terminate(upload_id: str, uploads: UploadsDep, user: UserDep,
              tus_resumable: TusHeader = None) -> Response:
    """Delete the upload, unfinished or finished; its bytes leave your quota."""
    check_version(tus_resumable)
    uploads.terminate(user, upload_id)
    return Response(status_code=204, headers=tus_headers())
