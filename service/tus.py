"""Resumable uploads with the tus protocol 1.0.0 (https://tus.io/protocols/resumable-upload):
core, creation, checksum, termination and expiration.

An upload is created with its length (reserved against the user's quota at once), then its
bytes arrive in any number of ``PATCH`` requests, each starting at the offset the server holds.
The bytes go to a part file on this host's disk (``DATA_DIR/uploads/resumable``), fsync'd before
the offset that counts them is recorded, so what the server confirmed survives a crash of the
API. A ``PATCH`` whose connection drops keeps what arrived, unless it carried an
``Upload-Checksum`` (then the piece cannot be verified and is dropped whole). When the last byte
has arrived the file is checked as ``POST /uploads`` checks it (415 when it is not LAS/LAZ),
moved into the storage, and becomes an ordinary upload with the same id: ``/uploads/<id>``.

The partial bytes stay on the API host that received them: with several API hosts, route a
resumable upload's requests to one host (or share ``DATA_DIR/uploads/resumable``).
"""

from __future__ import annotations

import asyncio
import base64
import binascii
import contextlib
import errno
import fcntl
import hashlib
import os
import socket
from collections.abc import AsyncIterator, Iterator
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from email.utils import format_datetime
from pathlib import Path
from typing import Any, BinaryIO

from starlette.requests import ClientDisconnect

from lidar_outliers.jobs import layout
from lidar_outliers.jobs.storage import StorageError
from lidar_outliers.jobs.store import QuotaExceeded, Resumable, Upload, User, parse_time
from service.jobs import JobService, las_facts, trajectory_facts
from service.problems import Problem, storage_unavailable
from service.uploads import _drain, too_large

VERSION = "1.0.0"
EXTENSIONS = "creation,checksum,termination,expiration"
#: ``Upload-Checksum`` algorithms, as tus names them.
CHECKSUMS = {"sha1": hashlib.sha1, "sha256": hashlib.sha256, "md5": hashlib.md5}
CONTENT_TYPE = "application/offset+octet-stream"
#: A PATCH without a checksum records its progress this often, so a crash of the API loses
#: at most this much of a long body.
COMMIT_BYTES = 64 * 1024**2
#: A PATCH whose client sends nothing for this long is ended (a link that died without a
#: reset would otherwise hold the upload's lock for ever); what arrived is kept.
IDLE_SECONDS = 60.0
HOST = socket.gethostname()
#: The first bytes of every LAS and LAZ file.
LAS_SIGNATURE = b"LASF"


def tus_headers(**more: str) -> dict[str, str]:
    return {"Tus-Resumable": VERSION, **more}


def problem(status: int, slug: str, detail: str, **headers: str) -> Problem:
    """A problem answer that also carries the protocol's version header."""
    return Problem(status, slug, detail, headers=tus_headers(**headers))


def http_date(stamp: str) -> str:
    """RFC 9110 date of an ISO 8601 time (``Upload-Expires``)."""
    return format_datetime(parse_time(stamp).astimezone(UTC), usegmt=True)


def iso(moment: datetime) -> str:
    return moment.isoformat(timespec="milliseconds").replace("+00:00", "Z")


def check_version(value: str | None) -> None:
    """412 unless the request speaks tus 1.0.0 (every request but OPTIONS must say so)."""
    if value != VERSION:
        raise problem(412, "tus-version", f"send `Tus-Resumable: {VERSION}` (got "
                      f"{value or 'none'}); this server speaks tus {VERSION}",
                      **{"Tus-Version": VERSION})


def parse_metadata(header: str | None) -> dict[str, str]:
    """``Upload-Metadata``: comma-separated ``key base64(value)`` pairs (the value optional)."""
    out: dict[str, str] = {}
    for pair in (header or "").split(","):
        pair = pair.strip()
        if not pair:
            continue
        key, _, value = pair.partition(" ")
        try:
            out[key] = base64.b64decode(value.strip(), validate=True).decode("utf-8")
        except (binascii.Error, UnicodeDecodeError):
            raise problem(400, "invalid-request", f"Upload-Metadata: the value of {key!r} is "
                          "not base64 of UTF-8 text") from None
    return out


def encode_metadata(values: dict[str, str]) -> str:
    return ",".join(f"{k} {base64.b64encode(v.encode()).decode()}" for k, v in values.items())


def parse_length(value: str | None, header: str) -> int:
    if value is None or not value.isdigit() or not value.isascii():
        raise problem(400, "invalid-request", f"{header}: a non-negative integer is required "
                      f"(got {value!r})")
    return int(value)


@dataclass(frozen=True)
class Checksum:
    algorithm: str
    digest: bytes

    def new(self) -> Any:
        return CHECKSUMS[self.algorithm]()


def parse_checksum(header: str | None) -> Checksum | None:
    """``Upload-Checksum: <algorithm> <base64 digest>``; 400 for an algorithm not offered."""
    if header is None:
        return None
    algorithm, _, encoded = header.strip().partition(" ")
    if algorithm not in CHECKSUMS:
        raise problem(400, "unsupported-checksum", f"Upload-Checksum: algorithm {algorithm!r} "
                      f"is not supported; use one of {', '.join(CHECKSUMS)}")
    try:
        digest = base64.b64decode(encoded.strip(), validate=True)
    except binascii.Error:
        digest = b""
    if len(digest) != CHECKSUMS[algorithm]().digest_size:
        raise problem(400, "invalid-request", "Upload-Checksum: the digest is not the base64 of "
                      f"a {algorithm} digest")
    return Checksum(algorithm, digest)


class Locked(Exception):
    """Another request is writing to the upload."""


@contextlib.contextmanager
def locked_part(path: Path) -> Iterator[BinaryIO]:
    """The part file opened for writing under an exclusive lock (``flock``: it holds between
    the API's processes and threads alike). Raises :class:`Locked` at once when held."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o600)
    handle = os.fdopen(fd, "r+b", buffering=0)
    try:
        try:
            fcntl.flock(handle.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN):
                raise Locked(str(path)) from None
            raise
        yield handle
    finally:
        handle.close()  # releases the lock


@dataclass
class Received:
    """What one PATCH left on disk: the offset after it, and whether its body ended normally."""

    offset: int
    complete: bool


class ResumableUploads:
    """The tus resources of one API process (``/uploads/tus``), on the service's store and
    storage."""

    def __init__(self, service: JobService) -> None:
        self.service = service
        self.store = service.store
        self.settings = service.settings

    # ---- helpers -----------------------------------------------------------------------------

    def part(self, upload_id: str) -> Path:
        return self.settings.resumable_dir / f"{upload_id}.part"

    def _expiry(self) -> str:
        return iso(datetime.now(UTC) + timedelta(hours=self.settings.resumable_expiry_hours))

    def options_headers(self) -> dict[str, str]:
        return tus_headers(**{
            "Tus-Version": VERSION, "Tus-Extension": EXTENSIONS,
            "Tus-Max-Size": str(self.settings.max_upload_bytes),
            "Tus-Checksum-Algorithm": ",".join(CHECKSUMS),
        })

    # ---- creation ----------------------------------------------------------------------------

    def create(self, user: User, length: int, metadata: dict[str, str]) -> Resumable:
        """A new upload of ``length`` bytes: 413 above MAX_UPLOAD_BYTES or the user's quota."""
        if length == 0:
            raise problem(400, "invalid-request", "Upload-Length: 0; an upload needs a file")
        if length > self.settings.max_upload_bytes:
            raise problem(413, "file-too-large", f"Upload-Length {length} exceeds the limit "
                          f"of {self.settings.max_upload_bytes} bytes (MAX_UPLOAD_BYTES)")
        kind = metadata.get("kind", "cloud")
        if kind not in ("cloud", "trajectory"):
            raise problem(400, "invalid-request", "Upload-Metadata: kind must be cloud or "
                          f"trajectory, got {kind!r}")
        name = os.path.basename(metadata.get("filename") or metadata.get("name") or "")
        name = name[:255] or ("trajectory.txt" if kind == "trajectory" else "cloud")
        # the user's expired uploads no longer hold quota
        self.service.expire_resumables(user_id=user.id)
        try:
            upload = self.store.add_resumable(
                user.id, name, kind, length, self._expiry(), HOST,
                max_stored_bytes=self.settings.max_stored_bytes_per_user)
        except QuotaExceeded as exc:
            refused = too_large(exc.left, True)
            raise problem(413, refused.slug, refused.detail) from None
        self.part(upload.id).parent.mkdir(parents=True, exist_ok=True)
        self.part(upload.id).touch()
        return upload

    # ---- look-ups ----------------------------------------------------------------------------

    def find(self, user: User, upload_id: str) -> Resumable | Upload:
        """The user's unfinished upload, or the finished one of that id; 404 for anything else
        (another user's uploads included), 410 once expired."""
        found = self.store.get_resumable(upload_id, user.id)
        if found is not None:
            if parse_time(found.expires) < datetime.now(UTC):
                raise problem(410, "upload-expired", f"upload {upload_id} expired at "
                              f"{found.expires} (RESUMABLE_EXPIRY_HOURS after its last PATCH); "
                              "create a new one")
            return found
        done = self.store.get_upload(upload_id, user.id)
        if done is None:
            raise problem(404, "no-such-upload", f"no upload {upload_id!r} of yours")
        return done

    def head_headers(self, upload: Resumable | Upload) -> dict[str, str]:
        if isinstance(upload, Upload):
            return tus_headers(**{"Upload-Offset": str(upload.bytes),
                                  "Upload-Length": str(upload.bytes),
                                  "Upload-Metadata": encode_metadata({"filename": upload.name}),
                                  "Cache-Control": "no-store"})
        return tus_headers(**{
            "Upload-Offset": str(upload.offset), "Upload-Length": str(upload.length),
            "Upload-Metadata": encode_metadata({"filename": upload.name, "kind": upload.kind}),
            "Upload-Expires": http_date(upload.expires), "Cache-Control": "no-store"})

    # ---- PATCH -------------------------------------------------------------------------------

    async def patch(self, user: User, upload_id: str, offset: int, content_length: int | None,
                    checksum: Checksum | None, body: AsyncIterator[bytes]) -> dict[str, str]:
        """Append a request body at ``offset``; the response headers of the 204."""
        upload = await asyncio.to_thread(self.find, user, upload_id)
        if isinstance(upload, Upload):
            if offset != upload.bytes:
                raise self._mismatch(offset, upload.bytes)
            if content_length:
                raise problem(413, "upload-length-exceeded", f"upload {upload_id} is complete "
                              f"({upload.bytes} bytes)")
            return self.head_headers(upload) | {"Upload-Href": f"/uploads/{upload.id}"}
        if content_length is not None and offset + content_length > upload.length:
            raise problem(413, "upload-length-exceeded", f"{content_length} bytes at offset "
                          f"{offset} exceed the Upload-Length of {upload.length}")
        part = self.part(upload.id)
        if not part.exists() and upload.host != HOST:
            raise problem(503, "service-unavailable", f"upload {upload.id} is being received by "
                          f"the API host {upload.host!r}; send its requests there")
        try:
            with locked_part(part) as handle:
                return await self._append(upload, handle, offset, checksum, body)
        except Locked:
            raise problem(423, "upload-locked", f"another request is writing to upload "
                          f"{upload_id}; retry after it ends (HEAD gives its offset)",
                          **{"Retry-After": "1"}) from None

    def _mismatch(self, sent: int, held: int) -> Problem:
        return problem(409, "offset-mismatch", f"Upload-Offset {sent} is not the upload's "
                       f"offset {held}; HEAD it and continue from there",
                       **{"Upload-Offset": str(held)})

    async def _append(self, upload: Resumable, handle: BinaryIO, offset: int,
                      checksum: Checksum | None, body: AsyncIterator[bytes]) -> dict[str, str]:
        # under the lock, the record is the truth: a PATCH that ended meanwhile moved it
        current = await asyncio.to_thread(self.store.get_resumable, upload.id, upload.user_id)
        if current is None:
            raise problem(404, "no-such-upload", f"upload {upload.id} was terminated")
        if offset != current.offset:
            raise self._mismatch(offset, current.offset)
        handle.truncate(offset)  # bytes of a PATCH that was cut before it was counted
        handle.seek(offset)
        received = await self._receive(current, handle, checksum, body)
        if received.offset < current.length:
            if received.offset != current.offset:
                await asyncio.to_thread(self._commit, current, handle, received.offset)
            return tus_headers(**{"Upload-Offset": str(received.offset),
                                  "Upload-Expires": http_date(self._expiry())})
        await asyncio.to_thread(os.fsync, handle.fileno())
        done = await asyncio.to_thread(self._finish, current)
        return tus_headers(**{"Upload-Offset": str(done.bytes), "Upload-Href":
                              f"/uploads/{done.id}"})

    def _commit(self, upload: Resumable, handle: BinaryIO, offset: int) -> None:
        """Record ``offset`` once the bytes before it are on disk."""
        os.fsync(handle.fileno())
        self.store.set_resumable_offset(upload.id, offset, self._expiry())

    async def _receive(self, upload: Resumable, handle: BinaryIO, checksum: Checksum | None,
                       body: AsyncIterator[bytes]) -> Received:
        """Write the body at the handle's position. With a checksum the piece counts whole or
        not at all (460 on a mismatch); without, a cut body keeps what arrived, and a long one
        is recorded every COMMIT_BYTES."""
        start = offset = upload.offset
        digest = checksum.new() if checksum else None
        committed = start
        chunks = body.__aiter__()
        try:
            while True:
                try:
                    chunk = await asyncio.wait_for(chunks.__anext__(), IDLE_SECONDS)
                except StopAsyncIteration:
                    break
                if offset + len(chunk) > upload.length:
                    handle.truncate(start if digest else offset)
                    raise problem(413, "upload-length-exceeded", "the body goes past the "
                                  f"Upload-Length of {upload.length}")
                handle.write(chunk)
                if digest is not None:
                    digest.update(chunk)
                elif offset - committed >= COMMIT_BYTES:
                    await asyncio.to_thread(self._commit, upload, handle, offset + len(chunk))
                    committed = offset + len(chunk)
                if start == 0 and offset < len(LAS_SIGNATURE) <= offset + len(chunk):
                    self._check_signature(upload, handle)
                offset += len(chunk)
        except Problem as refused:
            if refused.status == 413:
                await _drain(chunks)
            raise
        except (ClientDisconnect, TimeoutError):  # the client went away or fell silent
            if digest is not None:
                handle.truncate(start)
                return Received(start, False)
            return Received(offset, False)
        if checksum is not None and digest is not None and digest.digest() != checksum.digest:
            handle.truncate(start)
            raise problem(460, "checksum-mismatch", f"the {checksum.algorithm} of the "
                          f"{offset - start} bytes received differs from Upload-Checksum; "
                          "they were dropped, send them again",
                          **{"Upload-Offset": str(start)})
        return Received(offset, True)

    def _check_signature(self, upload: Resumable, handle: BinaryIO) -> None:
        """Refuse a cloud that is not LAS/LAZ as soon as its first bytes arrive, not after
        gigabytes: the upload is removed (415)."""
        if upload.kind != "cloud":
            return
        handle.flush()
        if os.pread(handle.fileno(), len(LAS_SIGNATURE), 0) != LAS_SIGNATURE:
            self.terminate_unfinished(upload)
            raise problem(415, "unsupported-media-type", f"{upload.name}: not a LAS/LAZ file "
                          "(it does not start with LASF); the upload was removed")

    def _finish(self, upload: Resumable) -> Upload:
        """The last byte arrived: check the file as POST /uploads does, store it, and turn the
        record into an ordinary upload of the same id. A file that fails the check is removed
        with its upload (415 / 422); a storage that fails leaves the upload at its previous
        offset (503; the client sends the last piece again)."""
        part = self.part(upload.id)
        try:
            if upload.kind == "trajectory":
                facts, suffix = trajectory_facts(part, upload.name), ".txt"
            else:
                facts = las_facts(part, upload.name)
                suffix = ".laz" if facts.get("compressed") else ".las"
        except Problem as refused:
            self.terminate_unfinished(upload)
            raise problem(refused.status, refused.slug, refused.detail +
                          "; the upload was removed") from None
        key = layout.upload_key(upload.user_id, upload.id, suffix)
        try:
            self.service.storage.put_file(key, part)
        except StorageError as exc:
            raise storage_unavailable(exc) from None
        try:
            done = self.store.complete_resumable(upload, key, facts)
        except BaseException:
            with contextlib.suppress(StorageError):
                self.service.storage.delete(key)
            raise
        part.unlink(missing_ok=True)
        return done

    # ---- termination -------------------------------------------------------------------------

    def terminate_unfinished(self, upload: Resumable) -> None:
        self.store.delete_resumable(upload.id)
        self.part(upload.id).unlink(missing_ok=True)

    def terminate(self, user: User, upload_id: str) -> None:
        """Delete an upload, unfinished (its reserved bytes are freed) or finished (jobs made
        from it keep their own copy)."""
        try:
            upload = self.find(user, upload_id)
        except Problem as refused:
            if refused.status != 410:
                raise
            upload = self.store.get_resumable(upload_id, user.id)  # expired: remove it anyway
            assert upload is not None
        if isinstance(upload, Upload):
            try:
                self.service.storage.delete(upload.key)
            except StorageError as exc:
                raise storage_unavailable(exc) from None
            self.store.delete_upload(upload.id)
            return
        try:
            with locked_part(self.part(upload.id)):
                self.terminate_unfinished(upload)
        except Locked:
            raise problem(423, "upload-locked", f"a request is writing to upload {upload_id}; "
                          "retry after it ends", **{"Retry-After": "1"}) from None
