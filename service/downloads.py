"""Downloads streamed from the storage, honouring HTTP range requests (RFC 9110, section 14).

- no ``Range`` (or a unit other than ``bytes``, or an ``If-Range`` that no longer matches):
  200 with the whole object;
- one satisfiable range: 206 with ``Content-Range: bytes first-last/size``;
- several: 206 ``multipart/byteranges`` (overlapping or adjacent ranges are merged first);
- malformed byte ranges, or none that the object can satisfy: 416 with
  ``Content-Range: bytes */size``.

Every answer says ``Accept-Ranges: bytes`` and carries the object's ``ETag`` and
``Last-Modified``, so a client can resume with ``If-Range``. ``HEAD`` answers the same headers
without the body.
"""

from __future__ import annotations

import secrets
from collections.abc import Iterator
from dataclasses import dataclass
from email.utils import formatdate, parsedate_to_datetime

from fastapi import Request, Response
from fastapi.responses import StreamingResponse

from lidar_outliers.jobs.storage import ObjectInfo, ObjectMissing, Storage, StorageError
from service.problems import Problem, storage_unavailable

#: More ranges than this in one request are refused (a request of many tiny ranges is abuse).
MAX_RANGES = 32


@dataclass(frozen=True)
class ByteRange:
    first: int
    last: int  # inclusive, as in Content-Range

    @property
    def length(self) -> int:
        return self.last - self.first + 1


class RangeNotSatisfiable(ValueError):
    """The Range header is malformed, or no range in it overlaps the object."""


def parse_range(header: str | None, size: int) -> list[ByteRange] | None:
    """The byte ranges a ``Range`` header asks of an object of ``size`` bytes, sorted and
    merged; None when the whole object is to be sent (no header, another range unit).

    Raises :class:`RangeNotSatisfiable` for malformed byte ranges or when none is satisfiable.
    """
    if not header or not header.strip():
        return None
    unit, sep, spec = header.partition("=")
    if not sep:
        raise RangeNotSatisfiable(f"malformed Range {header!r}")
    if unit.strip().lower() != "bytes":
        return None  # a unit we do not know: send the whole object
    specs = [s.strip() for s in spec.split(",") if s.strip()]
    if not specs:
        raise RangeNotSatisfiable("Range names no range")
    if len(specs) > MAX_RANGES:
        raise RangeNotSatisfiable(f"more than {MAX_RANGES} ranges")
    ranges = []
    for item in specs:
        first_text, dash, last_text = item.partition("-")
        first_text, last_text = first_text.strip(), last_text.strip()
        if not dash or not (first_text or last_text) or not all(
                t.isascii() and t.isdigit() for t in (first_text, last_text) if t):
            raise RangeNotSatisfiable(f"malformed range {item!r}")
        if not first_text:  # the last N bytes
            suffix = int(last_text)
            if suffix > 0 and size > 0:
                ranges.append(ByteRange(max(0, size - suffix), size - 1))
            continue
        first = int(first_text)
        if last_text and int(last_text) < first:
            raise RangeNotSatisfiable(f"range {item!r} ends before it starts")
        last = int(last_text) if last_text else size - 1
        if first < size:
            ranges.append(ByteRange(first, min(last, size - 1)))
    if not ranges:
        raise RangeNotSatisfiable(f"no range of {header!r} lies within the {size} bytes")
    ranges.sort(key=lambda r: r.first)
    merged = [ranges[0]]
    for r in ranges[1:]:
        if r.first <= merged[-1].last + 1:
            merged[-1] = ByteRange(merged[-1].first, max(merged[-1].last, r.last))
        else:
            merged.append(r)
    return merged


def _if_range_holds(value: str | None, info: ObjectInfo) -> bool:
    """Whether a range may be sent under ``If-Range`` (absent, or naming this version)."""
    if value is None:
        return True
    value = value.strip()
    if value.startswith('"'):
        return value == info.etag  # strong comparison
    if value.startswith("W/"):
        return False  # weak validators never match for ranges
    try:
        return int(parsedate_to_datetime(value).timestamp()) == int(info.modified)
    except (TypeError, ValueError):
        return False


def object_response(request: Request, storage: Storage, key: str, info: ObjectInfo,
                    media_type: str, filename: str | None = None) -> Response:
    """The object under ``key`` as a (partial) response to ``request``."""
    headers = {
        "Accept-Ranges": "bytes",
        "ETag": info.etag,
        "Last-Modified": formatdate(info.modified, usegmt=True),
    }
    if filename:
        headers["Content-Disposition"] = f'attachment; filename="{filename}"'
    ranges = None
    if _if_range_holds(request.headers.get("if-range"), info):
        try:
            ranges = parse_range(request.headers.get("range"), info.size)
        except RangeNotSatisfiable as exc:
            raise Problem(416, "range-not-satisfiable",
                          f"{exc}; the object has {info.size} bytes (ask e.g. bytes=0-1023)",
                          headers={"Content-Range": f"bytes */{info.size}"}) from None
    head = request.method == "HEAD"
    if ranges is None:
        headers["Content-Length"] = str(info.size)
        if head:
            return Response(status_code=200, headers=headers, media_type=media_type)
        return StreamingResponse(_open(storage, key), status_code=200, headers=headers,
                                 media_type=media_type)
    if len(ranges) == 1:
        r = ranges[0]
        headers["Content-Range"] = f"bytes {r.first}-{r.last}/{info.size}"
        headers["Content-Length"] = str(r.length)
        if head:
            return Response(status_code=206, headers=headers, media_type=media_type)
        return StreamingResponse(_open(storage, key, r.first, r.last), status_code=206,
                                 headers=headers, media_type=media_type)
    boundary = secrets.token_hex(12)
    parts = [(r, (f"--{boundary}\r\nContent-Type: {media_type}\r\nContent-Range: bytes "
                  f"{r.first}-{r.last}/{info.size}\r\n\r\n").encode()) for r in ranges]
    closing = f"\r\n--{boundary}--\r\n".encode()
    length = sum(len(h) + r.length for r, h in parts) + 2 * (len(parts) - 1) + len(closing)
    headers["Content-Length"] = str(length)
    multipart = f"multipart/byteranges; boundary={boundary}"
    if head:
        return Response(status_code=206, headers=headers, media_type=multipart)
    first = _open(storage, key, parts[0][0].first, parts[0][0].last)

    def body() -> Iterator[bytes]:
        for i, (r, part_head) in enumerate(parts):
            yield (b"\r\n" if i else b"") + part_head
            yield from first if i == 0 else storage.iter_range(key, r.first, r.last)
        yield closing

    return StreamingResponse(body(), status_code=206, headers=headers, media_type=multipart)


def _open(storage: Storage, key: str, first: int = 0, last: int | None = None) -> Iterator[bytes]:
    """Start reading before the answer's status is sent, so a missing object is still a 404."""
    try:
        return storage.iter_range(key, first, last)
    except ObjectMissing:
        raise Problem(404, "no-such-job", "the file was deleted meanwhile") from None
    except StorageError as exc:
        raise storage_unavailable(exc) from None
