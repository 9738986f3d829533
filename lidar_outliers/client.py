"""A Python client of the job service: upload, submit, wait, download.

::

    from lidar_outliers.client import Client

    with Client("http://127.0.0.1:8000", key) as api:
        job = api.submit("scan.las", inputs={"pipeline": [{"detector": "temporal"}]})
        api.wait(job["jobID"], lambda doc: print(doc["progress"], "%"))
        api.download(job["jobID"], "flagged.laz")       # LAZ from the suffix
        print(api.statistics(job["jobID"])["overall"])

Files go up and come down in chunks, never whole in memory; a download appears under its name
only once complete. Uploads are resumable where the server speaks tus 1.0.0 (``/uploads/tus``):
sent in pieces with checksums, continued from the server's offset after a dropped connection.
Every error, the server's or the connection's, raises :class:`ServiceError`
with the RFC 9457 problem document the server answered (``status``, ``title``, ``detail``).
"""

from __future__ import annotations

import base64
import hashlib
import io
import json
import os
import re
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, Literal

import httpx

from lidar_outliers.atomic import atomic_path
from lidar_outliers.errors import LidarOutliersError

#: ``progress(bytes_done, bytes_total)`` of an upload or a download (total 0 when unknown).
ByteProgress = Callable[[int, int], None]
#: Called with each status document while a job is polled.
JobProgress = Callable[[dict[str, Any]], None]
Source = str | os.PathLike[str]

CHUNK = 1024**2
#: Bytes per PATCH of a resumable upload: what a dropped connection costs at most.
TUS_CHUNK = 8 * 1024**2
TUS = {"Tus-Resumable": "1.0.0"}
#: Failed PATCHes in a row (no byte gained) before a resumable upload gives up.
TUS_ATTEMPTS = 6
FINISHED = ("successful", "failed", "dismissed")
_HREF = re.compile(r"^(?:https?://[^/]+)?/uploads/[0-9A-Za-z_-]+/?$")


class ServiceError(LidarOutliersError):
    """The service refused a request, a job failed, or the service could not be reached.

    ``problem`` is the RFC 9457 document (for a failed job one of type ``/problems/job-failed``
    with the job's status document under ``job``); ``status`` is None when no HTTP answer came.
    """

    def __init__(self, problem: dict[str, Any]) -> None:
        self.problem = problem
        self.status: int | None = problem.get("status")
        self.title: str = str(problem.get("title") or "Error")
        self.detail: str = str(problem.get("detail") or "")
        self.type: str = str(problem.get("type") or "about:blank")
        head = f"{self.status} {self.title}" if self.status else self.title
        super().__init__(f"{head}: {self.detail}" if self.detail else head)


def _problem_of(response: httpx.Response) -> ServiceError:
    """The problem document of an error answer; one made up when a proxy answered in HTML."""
    try:
        body = response.json()
    except ValueError:
        body = None
    if not isinstance(body, dict) or "title" not in body and "detail" not in body:
        text = " ".join(response.text.split())[:200]
        body = {"status": response.status_code, "title": response.reason_phrase or "Error",
                "detail": text or f"{response.request.method} {response.request.url}"}
    body.setdefault("status", response.status_code)
    return ServiceError(body)


class _CountingFile(io.FileIO):
    """A file that reports each read to a progress callback (httpx streams it in parts)."""

    def __init__(self, path: Path, progress: ByteProgress | None) -> None:
        super().__init__(path, "rb")
        self._progress = progress
        self._total = os.fstat(self.fileno()).st_size

    def read(self, size: int = -1) -> bytes:
        data = super().read(size)
        if self._progress is not None and data:
            self._progress(self.tell(), self._total)
        return data


def _chunks(path: Path, offset: int, progress: ByteProgress | None) -> Iterator[bytes]:
    total = path.stat().st_size
    with open(path, "rb") as file:
        file.seek(offset)
        while chunk := file.read(CHUNK):
            offset += len(chunk)
            if progress is not None:
                progress(offset, total)
            yield chunk


class Client:
    """The service at ``server`` (``http://host:8000``) as the user whose API key is ``key``."""

    def __init__(self, server: str, key: str, *, timeout: float = 60.0,
                 transport: httpx.BaseTransport | None = None,
                 resumable: bool | None = None, chunk_bytes: int = TUS_CHUNK,
                 retry_delay: float = 1.0) -> None:
        """``resumable``: upload with tus (True), in one request (False), or tus when the server
        offers it (None). ``chunk_bytes``: bytes per tus PATCH. ``retry_delay``: seconds before
        the first retry of a failed PATCH (doubling up to 30 s)."""
        self.server = server.rstrip("/")
        self._resumable = resumable
        self._checksum = "sha1"
        self.chunk_bytes = chunk_bytes
        self.retry_delay = retry_delay
        self._http = httpx.Client(
            base_url=self.server, headers={"Authorization": f"Bearer {key}"},
            timeout=httpx.Timeout(timeout, connect=min(timeout, 10.0)), transport=transport)

    def close(self) -> None:
        self._http.close()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ---- requests ----------------------------------------------------------------------------

    def _request(self, method: str, url: str, **kwargs: Any) -> httpx.Response:
        try:
            answer = self._http.request(method, url, **kwargs)
        except httpx.TransportError as exc:
            raise self._unreachable(exc) from None
        if answer.status_code >= 400:
            raise _problem_of(answer)
        return answer

    def _unreachable(self, exc: Exception) -> ServiceError:
        return ServiceError({"title": "Service unreachable",
                             "detail": f"{self.server}: {exc or type(exc).__name__}"})

    def _json(self, method: str, url: str, **kwargs: Any) -> dict[str, Any]:
        return self._request(method, url, **kwargs).json()

    # ---- files -------------------------------------------------------------------------------

    def resumable(self) -> bool:
        """Whether uploads go by tus: the server answers ``OPTIONS /uploads/tus`` with tus
        1.0.0 (asked once; the checksum is sha256 when offered, else sha1)."""
        if self._resumable is None:
            try:
                answer = self._http.options("/uploads/tus")
            except httpx.TransportError as exc:
                raise self._unreachable(exc) from None
            versions = answer.headers.get("tus-version", "").replace(" ", "").split(",")
            self._resumable = answer.is_success and "1.0.0" in versions
            offered = answer.headers.get("tus-checksum-algorithm", "").replace(" ", "")
            self._checksum = "sha256" if "sha256" in offered.split(",") else "sha1"
        return self._resumable

    def upload(self, path: Source, *, kind: Literal["cloud", "trajectory"] = "cloud",
               progress: ByteProgress | None = None) -> dict[str, Any]:
        """Store a file on the server for later jobs; returns ``{"id", "href", "name",
        "bytes"}`` (and more). ``kind="trajectory"`` for a trajectory text file.

        With tus (:meth:`resumable`) the file goes in pieces of ``chunk_bytes``, each with its
        checksum; after a dropped connection or a refused piece the upload continues from the
        offset the server reports (``HEAD``), so nothing it holds is sent again. Otherwise the
        file is one request, read as it is sent.
        """
        path = Path(path)
        if self.resumable():
            return self._upload_tus(path, kind, progress)
        size = path.stat().st_size
        return self._json(
            "POST", "/uploads", params={"name": path.name, "kind": kind},
            content=_chunks(path, 0, progress),
            headers={"Content-Type": "application/octet-stream", "Content-Length": str(size)},
            timeout=httpx.Timeout(self._http.timeout.connect, read=None, write=None, pool=None),
        )

    def _upload_tus(self, path: Path, kind: str,
                    progress: ByteProgress | None) -> dict[str, Any]:
        created = self.create_upload(path, kind)
        self.resume(created["location"], path, progress)
        return created

    def create_upload(self, path: Source, kind: str = "cloud") -> dict[str, Any]:
        """Create a tus upload for ``path`` (its size is reserved on the server); returns
        ``{"id", "href", "name", "bytes", "location"}``: :meth:`resume` sends to
        ``location``, jobs name ``href``."""
        path = Path(path)
        size = path.stat().st_size
        meta = ",".join(f"{k} {base64.b64encode(v.encode()).decode()}"
                        for k, v in (("filename", path.name), ("kind", kind)))
        created = self._request("POST", "/uploads/tus", headers=TUS | {
            "Upload-Length": str(size), "Upload-Metadata": meta})
        info = created.json()
        return {"id": info["id"], "href": info["href"], "name": info["name"], "bytes": size,
                "location": created.headers["location"]}

    def resume(self, location: str, path: Source,
               progress: ByteProgress | None = None) -> int:
        """Send ``path`` to the tus upload at ``location`` from the offset the server holds,
        until complete; returns the bytes sent. Transient failures (dropped connection, 5xx,
        409, 423, 460) are retried from the server's offset, up to TUS_ATTEMPTS in a row
        without progress."""
        path = Path(path)
        size = path.stat().st_size
        offset = self.upload_offset(location)
        sent = failures = 0
        delay = self.retry_delay
        with open(path, "rb") as file:
            while offset < size:
                file.seek(offset)
                piece = file.read(self.chunk_bytes)
                digest = hashlib.new(self._checksum, piece).digest()
                try:
                    answer = self._http.patch(
                        location, content=piece, headers=TUS | {
                            "Content-Type": "application/offset+octet-stream",
                            "Upload-Offset": str(offset),
                            "Upload-Checksum": f"{self._checksum} "
                                               f"{base64.b64encode(digest).decode()}"},
                        timeout=httpx.Timeout(self._http.timeout.connect, read=None,
                                              write=self._http.timeout.write, pool=None))
                    failed: Exception | None = None if answer.is_success else _problem_of(answer)
                except httpx.TransportError as exc:
                    answer, failed = None, self._unreachable(exc)
                sent += len(piece)
                if failed is None and answer is not None:
                    offset = int(answer.headers["upload-offset"])
                    failures, delay = 0, self.retry_delay
                    if progress is not None:
                        progress(offset, size)
                    continue
                status = getattr(failed, "status", None)
                if status is not None and status < 500 and status not in (409, 423, 460):
                    raise failed  # type: ignore[misc]
                failures += 1
                if failures >= TUS_ATTEMPTS:
                    raise failed  # type: ignore[misc]
                time.sleep(delay)
                delay = min(delay * 2, 30.0)
                offset = self.upload_offset(location, retries=TUS_ATTEMPTS)
        return sent

    def upload_offset(self, location: str, retries: int = 1) -> int:
        """The server's ``Upload-Offset`` of a tus upload (HEAD): the bytes it holds;
        retried ``retries`` times while the server is unreachable."""
        attempt = 0
        while True:
            try:
                return int(self._request("HEAD", location, headers=TUS)
                           .headers["upload-offset"])
            except ServiceError as exc:
                attempt += 1
                if exc.status is not None or attempt >= retries:
                    raise
                time.sleep(min(self.retry_delay * 2**attempt, 30.0))

    def delete_upload(self, upload: dict[str, Any] | str) -> None:
        """Delete an upload (its id, href or the dict :meth:`upload` returned) made with tus."""
        ident = upload["id"] if isinstance(upload, dict) else upload.rstrip("/").rsplit("/")[-1]
        self._request("DELETE", f"/uploads/tus/{ident}", headers=TUS)

    def submit(self, source: Source, process: str = "pipeline",
               inputs: dict[str, Any] | None = None, trajectory: Source | None = None, *,
               progress: ByteProgress | None = None) -> dict[str, Any]:
        """Queue a job; returns its status document (``jobID``, ``status``, ``progress`` ...).

        ``source``: a LAS/LAZ file, or the ``href`` of an earlier :meth:`upload`. ``inputs``:
        the process's inputs (``GET /processes/{process}`` gives them). ``trajectory``: a file
        of ``time x y z`` lines, or the href of a ``kind="trajectory"`` upload. Local files go
        up resumably where the server offers it (:meth:`upload`), are named in the job
        request, and deleted once the job holds its copy; otherwise they go in one multipart
        request.
        """
        inputs = dict(inputs or {})
        url = f"/processes/{process}/execution"
        all_local = not _is_href(source) and (trajectory is None or not _is_href(trajectory))
        if all_local and not self.resumable():
            return self._multipart(url, Path(source), inputs, trajectory, progress)
        made: list[dict[str, Any]] = []
        try:
            if _is_href(source):
                cloud = str(source)
            else:
                made.append(self.upload(source, progress=progress))
                cloud = made[-1]["href"]
            inputs["cloud"] = {"href": cloud}
            if trajectory is not None:
                if not _is_href(trajectory):
                    made.append(self.upload(trajectory, kind="trajectory"))
                href = str(trajectory) if _is_href(trajectory) else made[-1]["href"]
                inputs["trajectory"] = {"href": href}
            return self._json("POST", url, json={"inputs": inputs})
        finally:
            for upload in made:  # the job has its own copy (or was refused)
                if "location" in upload:
                    self._forget(upload)

    def _forget(self, upload: dict[str, Any]) -> None:
        try:
            self.delete_upload(upload)
        except ServiceError:  # retention removes it later
            pass

    def _multipart(self, url: str, path: Path, inputs: dict[str, Any],
                   trajectory: Source | None, progress: ByteProgress | None) -> dict[str, Any]:
        with _CountingFile(path, progress) as cloud:
            files: dict[str, Any] = {"file": (path.name, cloud, "application/octet-stream")}
            if trajectory is not None:
                traj = Path(trajectory)
                files["trajectory"] = (traj.name, traj.read_bytes(), "text/plain")
            return self._json(
                "POST", url, files=files, data={"inputs": json.dumps(inputs)},
                timeout=httpx.Timeout(self._http.timeout.connect, read=None, write=None,
                                      pool=None))

    def download(self, job_id: str, out_path: Source,
                 format: Literal["las", "laz"] | None = None,
                 keep: Literal["all", "inliers", "outliers"] = "all", *,
                 progress: ByteProgress | None = None) -> Path:
        """Write the job's flagged cloud to ``out_path``, whole or not at all.

        ``format``: las or laz; None takes it from the suffix of ``out_path`` (``.las``,
        ``.laz``), else the input's. ``keep``: all points, or the inliers or outliers only.
        """
        out = Path(out_path)
        if format is None and out.suffix.lower() in (".las", ".laz"):
            format = out.suffix.lower()[1:]  # type: ignore[assignment]
        params: dict[str, str] = {"keep": keep}
        if format is not None:
            params["format"] = format
        try:
            with self._http.stream("GET", f"/jobs/{job_id}/results/cloud", params=params,
                                   timeout=httpx.Timeout(self._http.timeout.connect,
                                                         read=None)) as answer:
                if answer.status_code >= 400:
                    answer.read()
                    raise _problem_of(answer)
                total = int(answer.headers.get("content-length") or 0)
                with atomic_path(out) as tmp, open(tmp, "wb") as file:
                    for chunk in answer.iter_bytes(CHUNK):
                        file.write(chunk)
                        if progress is not None:
                            progress(answer.num_bytes_downloaded, total)
        except httpx.TransportError as exc:
            raise self._unreachable(exc) from None
        return out

    # ---- jobs --------------------------------------------------------------------------------

    def status(self, job_id: str) -> dict[str, Any]:
        """The job's status document."""
        return self._json("GET", f"/jobs/{job_id}")

    def wait(self, job_id: str, progress_callback: JobProgress | None = None,
             timeout: float | None = None, *, interval: float = 0.25,
             max_interval: float = 5.0) -> dict[str, Any]:
        """Poll until the job is successful and return its status document.

        The first polls come quickly, later ones ever more slowly (up to ``max_interval``
        seconds apart). Raises :class:`ServiceError` when the job failed or was dismissed, and
        when ``timeout`` seconds pass first.
        """
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            doc = self.status(job_id)
            if progress_callback is not None:
                progress_callback(doc)
            if doc["status"] == "successful":
                return doc
            if doc["status"] in FINISHED:
                raise ServiceError({"type": "/problems/job-failed", "title": "Job failed",
                                    "detail": f"job {job_id} is {doc['status']}: "
                                    f"{doc.get('message') or 'no message'}", "job": doc})
            if deadline is not None and time.monotonic() + interval > deadline:
                raise ServiceError({"title": "Timed out", "detail": f"job {job_id} is still "
                                    f"{doc['status']} ({doc.get('progress', 0)} %) after "
                                    f"{timeout:g} s", "job": doc})
            time.sleep(interval)
            interval = min(interval * 1.5, max_interval)

    def statistics(self, job_id: str) -> dict[str, Any]:
        """The statistics document of a successful job."""
        return self._json("GET", f"/jobs/{job_id}/results/statistics")

    def jobs(self) -> list[dict[str, Any]]:
        """The status documents of all the user's jobs, newest first."""
        out: list[dict[str, Any]] = []
        url: str | None = "/jobs?limit=1000"
        while url is not None:
            page = self._json("GET", url)
            out.extend(page["jobs"])
            url = next((link["href"] for link in page.get("links", [])
                        if link.get("rel") == "next"), None)
        return out

    def dismiss(self, job_id: str) -> dict[str, Any]:
        """Cancel a queued or running job, or delete a finished one's files."""
        return self._json("DELETE", f"/jobs/{job_id}")


def _is_href(source: Source) -> bool:
    """An upload's href (``/uploads/<id>``), as opposed to the name of a local file."""
    return isinstance(source, str) and bool(_HREF.match(source)) and not os.path.exists(source)
