"""RFC 9457 problem details: every error the API answers is ``application/problem+json``.

Types of the OGC API - Processes standard keep their OGC URIs; the others are relative URIs
``/problems/<slug>`` that the API also serves as short human-readable descriptions.
"""

from __future__ import annotations

from typing import Any

from lidar_outliers.jobs.diskspace import DiskFull, is_disk_full

OGC = "http://www.opengis.net/def/exceptions/ogcapi-processes-1/1.0/"
MEDIA_TYPE = "application/problem+json"

#: slug -> (title, what to do). OGC slugs map to the standard's URIs.
PROBLEMS: dict[str, tuple[str, str]] = {
    "no-such-process": ("Unknown process", "GET /processes lists the processes."),
    "no-such-job": ("Unknown job", "GET /jobs lists your jobs; another user's jobs are not "
                    "visible."),
    "result-not-ready": ("Result not ready", "Poll GET /jobs/{id} until status is successful."),
    "invalid-parameter": ("Invalid parameter", "Fix the named input; GET /processes/{id} "
                          "gives each input's JSON Schema."),
    "invalid-request": ("Invalid request", "The request body or query is malformed."),
    "unauthorized": ("Missing or wrong API key", "Send `Authorization: Bearer <key>`; "
                     "`lidar-outliers users add NAME` creates a key."),
    "empty-file": ("Empty file", "The file sent has no bytes; send the LAS/LAZ file itself."),
    "insufficient-storage": ("Insufficient storage", "The server's disk is full; try again "
                             "later or ask its operator to free space."),
    "file-too-large": ("File too large", "Upload a smaller file or raise MAX_UPLOAD_BYTES."),
    "storage-quota-exceeded": ("Storage quota exceeded", "DELETE finished jobs to free space."),
    "unsupported-media-type": ("Not a LAS/LAZ file", "Send a LAS 1.0-1.4 or LAZ file."),
    "too-many-jobs": ("Too many active jobs", "Wait for a job to finish (see Retry-After) or "
                      "DELETE one."),
    "job-failed": ("Job failed", "The job's message says why."),
    "not-found": ("Not found", "GET /docs lists the routes."),
    "method-not-allowed": ("Method not allowed", "GET /docs lists the methods of each route."),
    "range-not-satisfiable": ("Range not satisfiable", "Ask for byte ranges within the "
                              "file's size (Content-Range: bytes */size), e.g. bytes=0-1023."),
    "service-unavailable": ("Service unavailable", "Redis, the workers, the database or the "
                            "file storage are not reachable."),
    "no-such-upload": ("Unknown upload", "POST /uploads/tus creates one; another user's "
                       "uploads are not visible."),
    "upload-expired": ("Upload expired", "An unfinished upload is deleted "
                       "RESUMABLE_EXPIRY_HOURS after its last PATCH; create a new one."),
    "offset-mismatch": ("Offset mismatch", "HEAD the upload and PATCH from its Upload-Offset."),
    "checksum-mismatch": ("Checksum mismatch", "The piece was dropped; PATCH it again from the "
                          "same Upload-Offset."),
    "unsupported-checksum": ("Checksum algorithm not supported", "OPTIONS /uploads/tus lists "
                             "them in Tus-Checksum-Algorithm."),
    "upload-locked": ("Upload busy", "Another request is writing to this upload; retry after "
                      "Retry-After seconds from the Upload-Offset HEAD gives."),
    "upload-length-exceeded": ("Past the upload's length", "Send no more than Upload-Length "
                               "bytes in all."),
    "tus-version": ("tus version not supported", "Send `Tus-Resumable: 1.0.0`."),
    "wrong-content-type": ("Wrong content type", "PATCH bodies are "
                           "`Content-Type: application/offset+octet-stream`."),
    "unsupported-output": ("Output format not possible", "Ask for the result in another "
                           "format (format=las)."),
    "internal-error": ("Internal error", "Report it with the time of the request."),
}
OGC_SLUGS = {"no-such-process", "no-such-job", "result-not-ready"}


def problem_type(slug: str) -> str:
    return OGC + slug if slug in OGC_SLUGS else f"/problems/{slug}"


class Problem(Exception):
    """An error to answer as problem details; raised by the service logic, rendered by the app."""

    def __init__(
        self,
        status: int,
        slug: str,
        detail: str,
        *,
        headers: dict[str, str] | None = None,
        **extra: Any,
    ) -> None:
        super().__init__(detail)
        self.status = status
        self.slug = slug
        self.detail = detail
        self.headers = headers or {}
        self.extra = extra

    def body(self) -> dict[str, Any]:
        title = PROBLEMS.get(self.slug, (self.slug.replace("-", " ").capitalize(), ""))[0]
        return {
            "type": problem_type(self.slug),
            "title": title,
            "status": self.status,
            "detail": self.detail,
            **self.extra,
        }


def insufficient_storage(exc: BaseException) -> Problem:
    """507 for a disk that is full (or would be with the request's file)."""
    detail = str(exc) if isinstance(exc, DiskFull) else f"the server's disk is full: {exc}"
    return Problem(507, "insufficient-storage", detail)


def upload_gone(parameter: str) -> Problem:
    """422 for a job named on an upload that was deleted while the job was being created."""
    message = "the upload was deleted before the job could take it; upload the file again"
    return Problem(422, "invalid-parameter", f"{parameter}: {message}",
                   errors=[{"parameter": parameter, "message": message}])


def storage_unavailable(exc: Exception) -> Problem:
    """503 for a storage that failed (the API goes on; the client may retry); 507 when what
    failed is a full disk."""
    if is_disk_full(exc):
        return insufficient_storage(exc)
    return Problem(503, "service-unavailable", f"the file storage is not usable: {exc}")
