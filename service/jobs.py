"""The service's logic, free of FastAPI: authentication, submission, status, results, dismissal,
retention. The routes in ``service.app`` only translate HTTP to these calls.

Files go through the storage interface only (:mod:`lidar_outliers.jobs.storage`): a received
request body is checked on this host, then moved into the storage; results are read from it.
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import uuid
from collections.abc import Callable
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any, TypeVar

from lidar_outliers import lasio, view
from lidar_outliers.errors import LidarOutliersError
from lidar_outliers.jobs import layout
from lidar_outliers.jobs.diskspace import DiskFull, check_room, is_disk_full
from lidar_outliers.jobs.documents import status_document  # noqa: F401 - routes import it here
from lidar_outliers.jobs.settings import Settings
from lidar_outliers.jobs.storage import (
    ObjectInfo,
    ObjectMissing,
    Storage,
    StorageError,
    open_storage,
)
from lidar_outliers.jobs.store import (
    ACTIVE,
    FINAL,
    Job,
    JobStatus,
    QuotaExceeded,
    Store,
    TooManyActiveJobs,
    Upload,
    User,
)
from lidar_outliers.params import PipelineParams
from lidar_outliers.tools.plot import render_preview
from lidar_outliers.trajectory import describe_trajectory, read_trajectory
from service import queue
from service.problems import Problem, insufficient_storage, storage_unavailable, upload_gone
from service.processes import CLOUD_INPUT, TRAJECTORY_INPUT, preflight, resolve_inputs
from service.uploads import too_large

T = TypeVar("T")

log = logging.getLogger(__name__)

#: Facts about the input shown in the status document.
FACT_KEYS = ("name", "bytes", "points", "las_version", "point_format", "compressed",
             "has_gps_time")

Enqueue = Callable[[str, int], None]


def las_facts(path: Path, name: str) -> dict[str, Any]:
    """Header facts of an uploaded file; 415 when it is not a LAS/LAZ file we can read."""
    try:
        facts = lasio.inspect_las(path)
    except LidarOutliersError as exc:  # LasFormatError and kin: one line about the file
        message = str(exc).replace(path.name, name)
        if name not in message:
            message = f"{name}: {message}"
        raise Problem(415, "unsupported-media-type", message) from None
    data = facts.to_dict()
    data["name"] = name
    data["bytes"] = path.stat().st_size
    return {k: data[k] for k in FACT_KEYS if k in data}


class JobService:
    def __init__(self, settings: Settings, store: Store, enqueue: Enqueue | None = None,
                 storage: Storage | None = None):
        self.settings = settings
        self.store = store
        self.storage = storage or open_storage(settings)
        self.enqueue = enqueue or (lambda job_id, priority: queue.enqueue(settings, job_id,
                                                                           priority))

    # ---- users -------------------------------------------------------------------------------

    def authenticate(self, authorization: str | None) -> User:
        scheme, _, key = (authorization or "").partition(" ")
        if scheme.lower() != "bearer" or not key.strip():
            raise Problem(401, "unauthorized", "missing API key: send `Authorization: Bearer "
                          "<key>`", headers={"WWW-Authenticate": "Bearer"})
        user = self.store.user_for_key(key.strip())
        if user is None:
            raise Problem(401, "unauthorized", "the API key is wrong or revoked",
                          headers={"WWW-Authenticate": 'Bearer error="invalid_token"'})
        return user

    def too_many_jobs(self, active: int) -> Problem:
        return Problem(
            429, "too-many-jobs",
            f"you have {active} queued or running jobs, the limit is "
            f"{self.settings.max_active_jobs_per_user}; wait for one to finish or DELETE one",
            headers={"Retry-After": str(self.settings.retry_after_seconds)},
        )

    def check_active_limit(self, user: User) -> int:
        """Number of the user's active jobs; 429 when no further one is allowed. An early
        answer before a body is read; :meth:`submit` checks again, atomically."""
        active = self.store.count_active(user.id)
        if active >= self.settings.max_active_jobs_per_user:
            raise self.too_many_jobs(active)
        return active

    def upload_limit(self, user: User) -> tuple[int, bool]:
        """Bytes this user may upload now, and whether the quota (not the file limit) binds."""
        left = self.settings.max_stored_bytes_per_user - self.store.stored_bytes(user.id)
        if left < self.settings.max_upload_bytes:
            return max(left, 0), True
        return self.settings.max_upload_bytes, False

    @property
    def incoming_dir(self) -> Path:
        return self.settings.incoming_dir

    def check_room(self, incoming: int, *, received: bool = False) -> None:
        """507 unless DATA_DIR's disk keeps MIN_FREE_BYTES free after ``incoming`` bytes and a
        result as large (``received``: the file is on the disk already)."""
        try:
            check_room(self.settings.data_dir, incoming, self.settings.min_free_bytes,
                       received=received)
        except DiskFull as exc:
            raise insufficient_storage(exc) from None

    # ---- uploads -----------------------------------------------------------------------------

    def store_upload(self, user: User, part: Path, name: str, kind: str = "cloud") -> Upload:
        """Keep a checked upload: a LAS/LAZ cloud (415 otherwise) or, with ``kind``
        ``"trajectory"``, a trajectory text file (422 otherwise). The quota check and the record
        are one transaction; the file is stored after it. The part is never left behind."""
        try:
            if kind == "trajectory":
                facts = trajectory_facts(part, name)
                suffix = ".txt"
            else:
                facts = las_facts(part, name)
                suffix = ".laz" if facts.get("compressed") else ".las"
            self.check_room(part.stat().st_size, received=True)
            upload_id = uuid.uuid4().hex
            key = layout.upload_key(user.id, upload_id, suffix)
            try:
                upload = self.store.add_upload(
                    user.id, name, key, part.stat().st_size, facts, upload_id=upload_id,
                    max_stored_bytes=self.settings.max_stored_bytes_per_user)
            except QuotaExceeded as exc:
                raise too_large(exc.left, True) from None
            try:
                self.storage.put_file(key, part, move=True)
            except BaseException as exc:
                self.store.delete_upload(upload.id)
                if isinstance(exc, StorageError):
                    raise storage_unavailable(exc) from None
                raise
            return upload
        finally:
            part.unlink(missing_ok=True)

    def find_upload(self, user: User, href: str, what: str = CLOUD_INPUT) -> Upload:
        upload_id = href.rstrip("/").rsplit("/", 1)[-1]
        upload = self.store.get_upload(upload_id, user.id)
        if upload is None or self._info(upload.key) is None:
            raise Problem(422, "invalid-parameter",
                          f"{what}.href: no upload {href!r} of yours; POST the file to /uploads "
                          "first and use the href it answers", errors=[
                              {"parameter": f"{what}.href", "message": "unknown upload"}])
        return upload

    def trajectory_upload(self, user: User, reference: Any) -> Upload:
        """The stored trajectory named by ``inputs.trajectory`` (``{"href": "/uploads/<id>"}``
        from ``POST /uploads?kind=trajectory``) of a JSON execute request."""
        href = reference.get("href") if isinstance(reference, dict) else None
        if not isinstance(href, str):
            raise Problem(422, "invalid-parameter", 'trajectory: give {"href": "/uploads/<id>"} '
                          "(POST /uploads?kind=trajectory first)",
                          errors=[{"parameter": "trajectory", "message": "missing href"}])
        return self.find_upload(user, href, TRAJECTORY_INPUT)

    def _info(self, key: str) -> ObjectInfo | None:
        try:
            return self.storage.info(key)
        except StorageError as exc:
            raise storage_unavailable(exc) from None

    def _upload_facts(self, upload: Upload, kind: str) -> dict[str, Any]:
        """The facts recorded with a stored upload of this kind. The file is read instead when
        none were recorded, or when it is of the other kind (which then fails as a received
        file would: 415 for a trajectory as the cloud, 422 for a cloud as the trajectory)."""
        stored_kind = "trajectory" if upload.key.endswith(".txt") else "cloud"
        if upload.facts is not None and stored_kind == kind:
            return dict(upload.facts)
        folder = layout.scratch(self.settings, "facts")
        try:
            local = folder / upload.key.rsplit("/", 1)[-1]
            self.storage.get_file(upload.key, local)
            if kind == "trajectory":
                return trajectory_facts(local, upload.name)
            return las_facts(local, upload.name)
        except ObjectMissing:
            raise upload_gone(kind) from None
        except StorageError as exc:
            raise storage_unavailable(exc) from None
        finally:
            shutil.rmtree(folder, ignore_errors=True)

    # ---- jobs --------------------------------------------------------------------------------

    def parse_inputs(self, process_id: str, inputs: Any) -> tuple[dict[str, Any], Any]:
        """Split the request's inputs into the pipeline parameters (validated) and the cloud."""
        if inputs is None:
            inputs = {}
        if not isinstance(inputs, dict):
            raise Problem(422, "invalid-parameter", "inputs must be a JSON object such as "
                          '{"n1": 5}', errors=[{"parameter": "inputs", "message": "not an object"}])
        inputs = dict(inputs)
        cloud = inputs.pop(CLOUD_INPUT, None)
        if TRAJECTORY_INPUT in inputs:
            raise Problem(422, "invalid-parameter", "trajectory: send the trajectory file as "
                          "the multipart part `trajectory` beside `file`, or as "
                          '{"href": "/uploads/<id>"} in a JSON request',
                          errors=[{"parameter": "trajectory", "message": "not an input value"}])
        params = resolve_inputs(process_id, inputs)
        return params.model_dump(mode="json"), cloud

    def submit(
        self, user: User, process_id: str, params: dict[str, Any], source: Path | Upload,
        name: str | None = None, *, trajectory: Path | Upload | None = None,
        trajectory_name: str = "trajectory.txt", subscriber: dict[str, str] | None = None,
    ) -> Job:
        """Create a job from a validated file and parameters and queue it.

        ``source`` (and ``trajectory``): a file received on this host (a request part: moved
        into the storage, and removed when refused) or a stored upload (copied inside the
        storage, so it serves further jobs). In order: the files are checked (415 / 422); the
        limits of active jobs (429) and stored bytes (413) are checked and the job recorded in
        one transaction (with ``subscriber``: its callback URIs, checked by the caller, and the
        API's base URL); its files are stored and it is queued. When that last step fails, the
        job is failed and its bytes released (503)."""
        received = [p for p in (source, trajectory) if isinstance(p, Path)]
        try:
            if isinstance(source, Upload):
                name = name or source.name
                facts = self._upload_facts(source, "cloud")
            else:
                name = name or source.name
                facts = las_facts(source, name)
            facts = {k: facts[k] for k in FACT_KEYS if k in facts} | {"name": name}
            preflight(PipelineParams.model_validate(params), int(facts.get("point_format", 0)),
                      bool(facts.get("has_gps_time", True)))
            if isinstance(trajectory, Upload):
                facts["trajectory"] = self._upload_facts(trajectory, "trajectory")
            elif trajectory is not None:
                facts["trajectory"] = trajectory_facts(trajectory, trajectory_name)
            laz = bool(facts.get("compressed"))
            size = sum(p.bytes if isinstance(p, Upload) else p.stat().st_size
                       for p in (source, trajectory) if p is not None)
            self.check_room(size, received=True)  # room for the result
            try:
                job = self.store.create_job(
                    user.id, process_id, params, facts, laz, stored_bytes=size,
                    job_id=os.urandom(16).hex(),
                    max_active=self.settings.max_active_jobs_per_user,
                    max_stored_bytes=self.settings.max_stored_bytes_per_user,
                    subscriber=subscriber)
            except TooManyActiveJobs as exc:
                raise self.too_many_jobs(exc.active) from None
            except QuotaExceeded as exc:
                raise too_large(exc.left, True) from None
            try:
                self._place(source, layout.input_key(job.id, laz))
                if trajectory is not None:
                    self._place(trajectory, layout.trajectory_key(job.id))
                # a user's n-th active job waits behind every other user's earlier ones
                self.enqueue(job.id, min(job.active_before, 9))
            except Exception as exc:
                if isinstance(exc, ObjectMissing) and any(
                        isinstance(p, Upload) for p in (source, trajectory)):
                    self._forget(job)  # never queued: no failed job is left behind
                    raise upload_gone("cloud") from None
                self._abandon(job, exc)
                if isinstance(exc, StorageError) or is_disk_full(exc):
                    raise storage_unavailable(exc) from None
                raise Problem(503, "service-unavailable",
                              f"the job queue (Redis) is not reachable: {exc}") from None
            return job
        finally:
            for path in received:  # stored or refused: a received part is not kept
                path.unlink(missing_ok=True)

    def _place(self, source: Path | Upload, key: str) -> None:
        if isinstance(source, Upload):
            self.storage.copy(source.key, key)
        else:
            self.storage.put_file(key, source, move=True)

    def _forget(self, job: Job) -> None:
        """A recorded job whose input went away before it was stored: no trace of it."""
        self._delete_files(job.id)
        self.store.delete_job(job.id)

    def _delete_files(self, job_id: str) -> None:
        """Delete a job's files; a storage that fails is logged (retention removes them
        later)."""
        try:
            self.storage.delete_prefix(layout.job_prefix(job_id))
        except StorageError:
            log.exception("could not remove the files of job %s", job_id)

    def _abandon(self, job: Job, exc: Exception) -> None:
        """A recorded job that could not be stored or queued: failed, its bytes released."""
        stored = isinstance(exc, StorageError) or is_disk_full(exc)
        what = "store the input" if stored else "queue the job"
        self.store.transition(job.id, JobStatus.failed, f"could not {what}: {exc}",
                              stored_bytes=0)
        self._delete_files(job.id)

    def poll(self, authorization: str | None, job_id: str) -> Job:
        """The caller's job ``job_id`` by key, in one database query (401, 404 otherwise)."""
        scheme, _, key = (authorization or "").partition(" ")
        if scheme.lower() != "bearer" or not key.strip():
            self.authenticate(authorization)  # raises the 401 of a missing key
        user, job = self.store.job_for_key(key.strip(), job_id)
        if user is None:
            self.authenticate(authorization)  # raises the 401 of a wrong key
        if job is None:
            raise Problem(404, "no-such-job", f"no job {job_id!r} of yours")
        return job

    def get(self, user: User, job_id: str) -> Job:
        job = self.store.get_job(job_id)
        if job is None or job.user_id != user.id:
            raise Problem(404, "no-such-job", f"no job {job_id!r} of yours")
        return job

    def dismiss(self, user: User, job_id: str) -> Job:
        """Cancel a queued or running job (the worker stops at its next progress report) or
        delete a finished job's files; the job stays listed as dismissed."""
        job = self.get(user, job_id)
        if job.status is not JobStatus.dismissed:
            job = self.store.transition(job_id, JobStatus.dismissed, "dismissed by the user",
                                        stored_bytes=0) or self.get(user, job_id)
        self._delete_files(job_id)
        return job

    def result(self, user: User, job_id: str, name: str) -> tuple[Job, str, ObjectInfo]:
        """A successful job's ``cloud`` or ``statistics``: the job, the key and its info."""
        job = self.get(user, job_id)
        if job.status is not JobStatus.successful:
            if job.status in ACTIVE:
                raise Problem(404, "result-not-ready",
                              f"job {job_id} is {job.status.value} ({job.progress} %); poll "
                              "GET /jobs/{id} until it is successful")
            raise Problem(404, "result-not-ready" if job.status is JobStatus.failed
                          else "no-such-job",
                          f"job {job_id} is {job.status.value}: {job.message}; it has no results")
        if name == "statistics":
            key = layout.statistics_key(job_id)
        else:
            key = layout.result_key(job_id, job.laz)
        info = self._info(key)
        if info is None:
            raise Problem(404, "no-such-job", f"the results of job {job_id} were deleted")
        return job, key, info

    def cloud(self, user: User, job_id: str, keep: str,
              laz: bool | None) -> tuple[str, ObjectInfo, bool]:
        """The flagged cloud, or a derived file (other format, inliers or outliers only) made
        on first request and stored beside the result: its key, its info, whether LAZ."""
        job, key, info = self.result(user, job_id, "cloud")
        laz = job.laz if laz is None else laz
        if keep == "all" and laz == job.laz:
            return key, info, laz
        try:
            lasio.check_laz_output(job.facts.get("name", "the result"),
                                   int(job.facts.get("point_format", -1)), laz)
        except LidarOutliersError as exc:
            raise Problem(422, "unsupported-output", str(exc)) from None

        def make(result: Path, out: Path) -> None:
            if keep == "all":
                lasio.convert(result, out, laz)
            else:
                lasio.write_filtered(result, out, keep, laz)

        derived = layout.derived_key(job_id, keep, laz)
        return derived, self._derive(job, derived, make), laz

    def preview(self, user: User, job_id: str) -> tuple[str, ObjectInfo]:
        """A PNG of the flagged cloud, rendered on first request and stored beside it."""
        job, _, _ = self.result(user, job_id, "cloud")
        key = layout.preview_key(job_id)
        return key, self._derive(job, key, render_preview, statistics=True)

    def view_points(self, user: User, job_id: str) -> tuple[str, ObjectInfo]:
        """The viewer's default decimation of the flagged cloud, made once and stored."""
        job, _, _ = self.result(user, job_id, "cloud")
        key = layout.view_points_key(job_id)

        def make(result: Path, out: Path) -> None:
            out.write_bytes(view.view_points(result))

        return key, self._derive(job, key, make)

    def view_points_bytes(self, user: User, job_id: str, max_points: int) -> bytes:
        """Another decimation, made on each request (not kept: any size may be asked for)."""
        job, _, _ = self.result(user, job_id, "cloud")
        return self._with_local_result(job, lambda result: view.view_points(result, max_points))

    def _derive(self, job: Job, key: str, make: Callable[[Path, Path], Any],
                statistics: bool = False) -> ObjectInfo:
        """The object under ``key``, made from a local copy of the job's result when missing.
        Two requests at once may both make it; each put is whole and they are equal."""
        info = self._info(key)
        if info is not None:
            return info

        def build(result: Path) -> None:
            out = result.with_name("out-" + key.rsplit("/", 1)[-1])
            make(result, out)
            self.storage.put_file(key, out, move=True)

        self._with_local_result(job, build, statistics)
        now = self.store.get_job(job.id)
        if now is None or now.status is not JobStatus.successful:
            # dismissed while it was made: dismissal deletes the job's files before or after
            # this put; after, the status says so here
            try:
                self.storage.delete(key)
            except StorageError:
                log.exception("could not remove %s of a dismissed job", key)
            raise Problem(404, "no-such-job", f"the results of job {job.id} were deleted")
        info = self._info(key)
        if info is None:  # dismissed meanwhile
            raise Problem(404, "no-such-job", f"the results of job {job.id} were deleted")
        return info

    def _with_local_result(self, job: Job, use: Callable[[Path], T],
                           statistics: bool = False) -> T:
        """``use(path)`` of a local copy of the job's result in a scratch folder (removed
        afterwards); with ``statistics`` the statistics lie beside it."""
        folder = layout.scratch(self.settings, f"derive-{job.id}")
        try:
            result_key = layout.result_key(job.id, job.laz)
            result = folder / result_key.rsplit("/", 1)[-1]
            self.storage.get_file(result_key, result)
            if statistics:  # beside the result, where the preview looks for it
                self.storage.get_file(layout.statistics_key(job.id), folder / "statistics.json")
            return use(result)
        except ObjectMissing:
            raise Problem(404, "no-such-job",
                          f"the results of job {job.id} were deleted") from None
        except StorageError as exc:
            raise storage_unavailable(exc) from None
        finally:
            shutil.rmtree(folder, ignore_errors=True)

    # ---- retention ---------------------------------------------------------------------------

    def cleanup(self, now: datetime | None = None) -> int:
        """Delete finished jobs and uploads older than RETENTION_DAYS; return how many."""
        now = now or datetime.now(UTC)
        cutoff = (now - timedelta(days=self.settings.retention_days)).isoformat(
            timespec="milliseconds").replace("+00:00", "Z")
        removed = 0
        for job in self.store.jobs_finished_before(cutoff):
            if job.status in FINAL:
                self.storage.delete_prefix(layout.job_prefix(job.id))
                self.store.delete_job(job.id)
                removed += 1
        for upload in self.store.uploads_created_before(cutoff):
            self.storage.delete(upload.key)
            self.store.delete_upload(upload.id)
            removed += 1
        for part in self.incoming_dir.glob("*.part") if self.incoming_dir.exists() else []:
            if datetime.fromtimestamp(part.stat().st_mtime, UTC) < now - timedelta(days=1):
                part.unlink(missing_ok=True)
        removed += self.expire_resumables(now)
        layout.sweep_scratch(self.settings, older_than=self.settings.visibility_timeout)
        return removed


    def expire_resumables(self, now: datetime | None = None, user_id: int | None = None) -> int:
        """Delete unfinished resumable uploads past their expiry, which frees the bytes they
        reserved, with their partial files on this host; also partial files of this host that
        no record could still use (written to longer ago than any upload stays). Returns how
        many records went."""
        now = now or datetime.now(UTC)
        stamp = now.isoformat(timespec="milliseconds").replace("+00:00", "Z")
        expired = self.store.resumables_expired(stamp, user_id)
        folder = self.settings.resumable_dir
        for upload in expired:
            self.store.delete_resumable(upload.id)
            (folder / f"{upload.id}.part").unlink(missing_ok=True)
        if user_id is None and folder.is_dir():
            cutoff = now - timedelta(hours=self.settings.resumable_expiry_hours + 1)
            for part in folder.glob("*.part"):
                with contextlib.suppress(FileNotFoundError):
                    if datetime.fromtimestamp(part.stat().st_mtime, UTC) < cutoff:
                        part.unlink()
        return len(expired)


def trajectory_facts(path: Path, name: str) -> dict[str, Any]:
    """Samples and time span of a received trajectory; 422 naming the line when unusable."""
    try:
        traj = read_trajectory(path, name)
    except LidarOutliersError as exc:
        raise Problem(422, "invalid-parameter", str(exc),
                      errors=[{"parameter": "trajectory", "message": str(exc)}]) from None
    return describe_trajectory(traj, name)
