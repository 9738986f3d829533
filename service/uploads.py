"""Request bodies streamed to disk chunk by chunk, never held whole in memory.

Both readers stop writing as soon as the limit is passed and answer 413; they keep reading (and
discarding) a bounded amount of the rest of the body so that the client receives the answer
instead of a reset connection.
"""

from __future__ import annotations

import os
import uuid
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

from python_multipart.multipart import MultipartParser, parse_options_header

from lidar_outliers.jobs.diskspace import is_disk_full
from service.problems import Problem, insufficient_storage

#: After a 413, read at most this much more of the body before giving up on the connection.
DRAIN_LIMIT = 64 * 1024**2
#: Largest non-file multipart part (the JSON inputs).
MAX_FIELD_BYTES = 1024**2


@dataclass
class Received:
    path: Path | None
    filename: str
    size: int
    fields: dict[str, str]
    #: The optional part ``trajectory`` (a text file), on disk like ``file``.
    trajectory: Path | None = None
    trajectory_name: str = ""

    def remove(self) -> None:
        """Delete the received parts (a refused request keeps nothing)."""
        for path in (self.path, self.trajectory):
            if path is not None:
                path.unlink(missing_ok=True)


def too_large(limit: int, quota: bool) -> Problem:
    if quota:
        return Problem(413, "storage-quota-exceeded",
                       f"the upload would exceed your storage quota ({limit} bytes left); "
                       "DELETE finished jobs first")
    return Problem(413, "file-too-large",
                   f"the file is larger than the limit of {limit} bytes (MAX_UPLOAD_BYTES)")


def empty_file(detail: str) -> Problem:
    return Problem(400, "empty-file", detail)


async def _drain(stream: AsyncIterator[bytes]) -> None:
    seen = 0
    async for chunk in stream:
        seen += len(chunk)
        if seen > DRAIN_LIMIT:
            return


def declared_size(content_length: str | None) -> int:
    """The request's Content-Length, 0 when absent (or not a number)."""
    return int(content_length) if content_length and content_length.isdigit() else 0


def refuse_declared_size(content_length: str | None, limit: int, quota: bool,
                         overhead: int) -> None:
    """413 at once when the declared body cannot fit, before a byte of it is read."""
    if content_length and content_length.isdigit() and int(content_length) > limit + overhead:
        raise too_large(limit, quota)


#: Bytes of a multipart body besides the file: the inputs part and the part headers.
MULTIPART_OVERHEAD = MAX_FIELD_BYTES + 64 * 1024


def part_path(directory: Path) -> Path:
    directory.mkdir(parents=True, exist_ok=True)
    return directory / f"{uuid.uuid4().hex}.part"


async def receive_raw(
    stream: AsyncIterator[bytes], directory: Path, limit: int, quota: bool, filename: str
) -> Received:
    """Write a raw request body to a new ``.part`` file in ``directory``."""
    path = part_path(directory)
    size = 0
    try:
        with open(path, "wb") as out:
            async for chunk in stream:
                size += len(chunk)
                if size > limit:
                    raise too_large(limit, quota)
                out.write(chunk)
    except Problem:
        path.unlink(missing_ok=True)
        await _drain(stream)
        raise
    except OSError as exc:
        path.unlink(missing_ok=True)
        if not is_disk_full(exc):
            raise
        await _drain(stream)
        raise insufficient_storage(exc) from None
    except BaseException:
        path.unlink(missing_ok=True)
        raise
    if size == 0:
        path.unlink(missing_ok=True)
        raise empty_file(f"{filename}: the file is empty (0 bytes); send the LAS/LAZ file as "
                         "the body (curl --data-binary @cloud.las)")
    return Received(path=path, filename=filename, size=size, fields={})


class _FormReader:
    """Callbacks for python-multipart: parts ``file`` and ``trajectory`` go to disk, others to
    memory. Their sizes together count against the limit."""

    def __init__(self, directory: Path, limit: int, quota: bool) -> None:
        self.directory = directory
        self.limit = limit
        self.quota = quota
        self.path: Path | None = None
        self.filename = ""
        self.size = 0
        self.fields: dict[str, str] = {}
        self.trajectory: Path | None = None
        self.trajectory_name = ""
        self.trajectory_size = 0
        self._out: BinaryIO | None = None
        self._name = ""
        self._buffer = bytearray()
        self._header_field = bytearray()
        self._header_value = bytearray()
        self._headers: dict[str, bytes] = {}

    def callbacks(self) -> dict:
        return {
            "on_part_begin": self.part_begin,
            "on_part_data": self.part_data,
            "on_part_end": self.part_end,
            "on_header_field": lambda d, s, e: self._header_field.extend(d[s:e]),
            "on_header_value": lambda d, s, e: self._header_value.extend(d[s:e]),
            "on_header_end": self.header_end,
            "on_headers_finished": self.headers_finished,
        }

    def part_begin(self) -> None:
        self._headers = {}
        self._name = ""
        self._buffer = bytearray()

    def header_end(self) -> None:
        self._headers[bytes(self._header_field).decode("latin-1").lower()] = bytes(
            self._header_value
        )
        self._header_field = bytearray()
        self._header_value = bytearray()

    def headers_finished(self) -> None:
        _, options = parse_options_header(self._headers.get("content-disposition", b""))
        self._name = options.get(b"name", b"").decode("utf-8", "replace")
        if self._name == "file":
            if self.path is not None:
                raise Problem(400, "invalid-request", "send exactly one part named `file`")
            self.filename = options.get(b"filename", b"cloud.las").decode("utf-8", "replace")
            self.path = part_path(self.directory)
            self._out = open(self.path, "wb")  # noqa: SIM115 - closed in part_end / cleanup
        elif self._name == "trajectory":
            if self.trajectory is not None:
                raise Problem(400, "invalid-request", "send at most one part named `trajectory`")
            self.trajectory_name = options.get(b"filename", b"trajectory.txt").decode(
                "utf-8", "replace")
            self.trajectory = part_path(self.directory)
            self._out = open(self.trajectory, "wb")  # noqa: SIM115 - closed in part_end

    def part_data(self, data: bytes, start: int, end: int) -> None:
        if self._out is not None:
            if self._name == "trajectory":
                self.trajectory_size += end - start
            else:
                self.size += end - start
            if self.size + self.trajectory_size > self.limit:
                raise too_large(self.limit, self.quota)
            self._out.write(data[start:end])
        else:
            self._buffer.extend(data[start:end])
            if len(self._buffer) > MAX_FIELD_BYTES:
                raise Problem(400, "invalid-request",
                              f"form field {self._name!r} is larger than {MAX_FIELD_BYTES} bytes")

    def part_end(self) -> None:
        if self._out is not None:
            self._out.close()
            self._out = None
        elif self._name:
            self.fields[self._name] = self._buffer.decode("utf-8", "replace")

    def cleanup(self) -> None:
        if self._out is not None:
            self._out.close()
            self._out = None
        for path in (self.path, self.trajectory):
            if path is not None:
                path.unlink(missing_ok=True)


async def receive_multipart(
    stream: AsyncIterator[bytes], content_type: str, directory: Path, limit: int, quota: bool
) -> Received:
    """Parse ``multipart/form-data`` as it arrives: part ``file`` to disk, other parts kept."""
    _, options = parse_options_header(content_type)
    boundary = options.get(b"boundary")
    if not boundary:
        raise Problem(400, "invalid-request", "multipart/form-data without a boundary")
    reader = _FormReader(directory, limit, quota)
    parser = MultipartParser(boundary, reader.callbacks())
    try:
        async for chunk in stream:
            parser.write(chunk)
        parser.finalize()
    except Problem:
        reader.cleanup()
        await _drain(stream)
        raise
    except Exception as exc:
        reader.cleanup()
        if is_disk_full(exc):
            await _drain(stream)
            raise insufficient_storage(exc) from None
        raise Problem(400, "invalid-request", f"malformed multipart body: {exc}") from None
    except BaseException:
        reader.cleanup()
        raise
    if reader.path is None:
        reader.cleanup()
        raise Problem(400, "invalid-request",
                      "no file: send the LAS/LAZ cloud in a multipart part named `file` "
                      "(curl -F file=@cloud.las)")
    if reader.size == 0:
        reader.cleanup()
        name = os.path.basename(reader.filename) or "file"
        raise empty_file(f"{name}: the file is empty (0 bytes); the part `file` must hold the "
                         "LAS/LAZ cloud")
    if reader.trajectory is not None and reader.trajectory_size == 0:
        reader.cleanup()
        raise Problem(422, "invalid-parameter", "trajectory: the part `trajectory` is empty",
                      errors=[{"parameter": "trajectory", "message": "empty"}])
    return Received(path=reader.path, filename=os.path.basename(reader.filename) or "cloud.las",
                    size=reader.size, fields=reader.fields, trajectory=reader.trajectory,
                    trajectory_name=os.path.basename(reader.trajectory_name) or "trajectory.txt")
