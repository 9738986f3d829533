"""The service's logic, free of FastAPI: authentication, submission, status, results, dismissal,
retention. The routes in ``service.app`` only translate HTTP to these calls.
"""

from __future__ import annotations

import logging
import os
import shutil
from collections.abc import Callable
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

from lidar_outliers import lasio
from lidar_outliers.errors import LidarOutliersError
from lidar_outliers.jobs import layout
from lidar_outliers.jobs.settings import Settings
from lidar_outliers.jobs.store import ACTIVE, FINAL, Job, JobStatus, Store, Upload, User
from lidar_outliers.params import PipelineParams
from lidar_outliers.tools.plot import render_preview
from lidar_outliers.trajectory import describe_trajectory, read_trajectory
from service import queue
from service.problems import Problem
from service.processes import CLOUD_INPUT, TRAJECTORY_INPUT, preflight, resolve_inputs

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
    def __init__(self, settings: Settings, store: Store, enqueue: Enqueue | None = None):
        self.settings = settings
        self.store = store
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

    def check_active_limit(self, user: User) -> int:
        """Number of the user's active jobs; 429 when no further one is allowed."""
        active = self.store.count_active(user.id)
        if active >= self.settings.max_active_jobs_per_user:
            raise Problem(
                429, "too-many-jobs",
                f"you have {active} queued or running jobs, the limit is "
                f"{self.settings.max_active_jobs_per_user}; wait for one to finish or DELETE one",
                headers={"Retry-After": str(self.settings.retry_after_seconds)},
            )
        return active

    def upload_limit(self, user: User) -> tuple[int, bool]:
        """Bytes this user may upload now, and whether the quota (not the file limit) binds."""
        left = self.settings.max_stored_bytes_per_user - self.store.stored_bytes(user.id)
        if left < self.settings.max_upload_bytes:
            return max(left, 0), True
        return self.settings.max_upload_bytes, False

    @property
    def incoming_dir(self) -> Path:
        return self.settings.uploads_dir / "incoming"

    # ---- uploads -----------------------------------------------------------------------------

    def store_upload(self, user: User, part: Path, name: str, kind: str = "cloud") -> Upload:
        """Keep a checked upload: a LAS/LAZ cloud (415 otherwise) or, with ``kind``
        ``"trajectory"``, a trajectory text file (422 otherwise)."""
        if kind == "trajectory":
            try:
                trajectory_facts(part, name)
            except BaseException:
                part.unlink(missing_ok=True)
                raise
            suffix = ".txt"
        else:
            facts = las_facts_or_remove(part, name)
            suffix = ".laz" if facts.get("compressed") else ".las"
        folder = self.settings.uploads_dir / str(user.id)
        folder.mkdir(parents=True, exist_ok=True)
        final = folder / (part.stem + suffix)
        os.replace(part, final)
        return self.store.add_upload(user.id, name, final, final.stat().st_size)

    def find_upload(self, user: User, href: str, what: str = CLOUD_INPUT) -> Upload:
        upload_id = href.rstrip("/").rsplit("/", 1)[-1]
        upload = self.store.get_upload(upload_id, user.id)
        if upload is None or not Path(upload.path).exists():
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
        self, user: User, process_id: str, params: dict[str, Any], source: Path, name: str,
        *, move: bool, trajectory: Path | None = None, trajectory_name: str = "trajectory.txt",
        move_trajectory: bool = True,
    ) -> Job:
        """Create a job from a validated file and parameters and queue it.

        ``move``: the source is a fresh upload part (renamed into the job folder); otherwise it
        is a stored upload (hard-linked, so the upload can serve further jobs). ``trajectory``:
        an optional trajectory file, checked (422 when unusable) and moved (a received part,
        ``move_trajectory``) or linked (a stored upload) into the job folder; its facts appear
        in the job's ``input_file``."""
        try:
            active = self.check_active_limit(user)
            facts = las_facts(source, name)
            preflight(PipelineParams.model_validate(params), int(facts.get("point_format", 0)))
            if trajectory is not None:
                facts["trajectory"] = trajectory_facts(trajectory, trajectory_name)
        except BaseException:
            if move:  # a refused upload is not kept
                source.unlink(missing_ok=True)
            if trajectory is not None and move_trajectory:
                trajectory.unlink(missing_ok=True)
            raise
        job_id = os.urandom(16).hex()
        laz = bool(facts.get("compressed"))
        target = layout.input_path(self.settings, job_id, laz)
        target.parent.mkdir(parents=True, exist_ok=True)
        _place(source, target, move)
        stored = target.stat().st_size
        if trajectory is not None:
            traj_target = layout.trajectory_path(self.settings, job_id)
            _place(trajectory, traj_target, move_trajectory)
            stored += traj_target.stat().st_size
        job = self.store.create_job(user.id, process_id, params, facts, laz,
                                    stored_bytes=stored, job_id=job_id)
        try:
            # a user's n-th active job waits behind every other user's earlier ones
            self.enqueue(job.id, min(active, 9))
        except Exception as exc:
            self.store.transition(job.id, JobStatus.failed, f"could not queue the job: {exc}")
            shutil.rmtree(target.parent, ignore_errors=True)
            raise Problem(503, "service-unavailable",
                          f"the job queue (Redis) is not reachable: {exc}") from None
        return job

    def get(self, user: User, job_id: str) -> Job:
        job = self.store.get_job(job_id)
        if job is None or job.user_id != user.id:
            raise Problem(404, "no-such-job", f"no job {job_id!r} of yours")
        return job

    def list_jobs(self, user: User, limit: int, offset: int) -> tuple[list[Job], int]:
        return self.store.list_jobs(user.id, limit, offset)

    def dismiss(self, user: User, job_id: str) -> Job:
        """Cancel a queued or running job (the worker stops at its next progress report) or
        delete a finished job's files; the job stays listed as dismissed."""
        job = self.get(user, job_id)
        if job.status is not JobStatus.dismissed:
            job = self.store.transition(job_id, JobStatus.dismissed, "dismissed by the user",
                                        stored_bytes=0) or self.get(user, job_id)
        shutil.rmtree(layout.job_dir(self.settings, job_id), ignore_errors=True)
        return job

    def result_file(self, user: User, job_id: str, name: str) -> tuple[Job, Path]:
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
            path = layout.statistics_path(self.settings, job_id)
        else:
            path = layout.result_path(self.settings, job_id, job.laz)
        if not path.exists():
            raise Problem(404, "no-such-job", f"the results of job {job_id} were deleted")
        return job, path

    def cloud_file(self, user: User, job_id: str, keep: str, laz: bool | None) -> Path:
        """The flagged cloud, or a derived file (other format, inliers or outliers only),
        made on first request and kept beside the result."""
        job, path = self.result_file(user, job_id, "cloud")
        laz = job.laz if laz is None else laz
        if keep == "all" and laz == job.laz:
            return path
        derived = path.with_name(f"cloud-{keep}.{'laz' if laz else 'las'}")
        if not derived.exists():
            if keep == "all":
                lasio.convert(path, derived, laz)
            else:
                lasio.write_filtered(path, derived, keep, laz)
        return derived

    def preview_file(self, user: User, job_id: str) -> Path:
        _, path = self.result_file(user, job_id, "cloud")
        png = path.with_name("preview.png")
        if not png.exists():
            render_preview(path, png)
        return png

    # ---- retention ---------------------------------------------------------------------------

    def cleanup(self, now: datetime | None = None) -> int:
        """Delete finished jobs and uploads older than RETENTION_DAYS; return how many."""
        now = now or datetime.now(UTC)
        cutoff = (now - timedelta(days=self.settings.retention_days)).isoformat(
            timespec="milliseconds").replace("+00:00", "Z")
        removed = 0
        for job in self.store.jobs_finished_before(cutoff):
            if job.status in FINAL:
                shutil.rmtree(layout.job_dir(self.settings, job.id), ignore_errors=True)
                self.store.delete_job(job.id)
                removed += 1
        for upload in self.store.uploads_created_before(cutoff):
            Path(upload.path).unlink(missing_ok=True)
            self.store.delete_upload(upload.id)
            removed += 1
        for part in self.incoming_dir.glob("*.part") if self.incoming_dir.exists() else []:
            if datetime.fromtimestamp(part.stat().st_mtime, UTC) < now - timedelta(days=1):
                part.unlink(missing_ok=True)
        return removed


def _place(source: Path, target: Path, move: bool) -> None:
    """Rename a received part into place, or hard-link (copy) a stored upload."""
    if move:
        os.replace(source, target)
        return
    try:
        os.link(source, target)
    except OSError:
        shutil.copyfile(source, target)


def trajectory_facts(path: Path, name: str) -> dict[str, Any]:
    """Samples and time span of a received trajectory; 422 naming the line when unusable."""
    try:
        traj = read_trajectory(path, name)
    except LidarOutliersError as exc:
        raise Problem(422, "invalid-parameter", str(exc),
                      errors=[{"parameter": "trajectory", "message": str(exc)}]) from None
    return describe_trajectory(traj, name)


def las_facts_or_remove(part: Path, name: str) -> dict[str, Any]:
    try:
        return las_facts(part, name)
    except BaseException:
        part.unlink(missing_ok=True)
        raise


def status_document(job: Job, base_url: str = "") -> dict[str, Any]:
    """OGC API - Processes statusInfo plus the resolved inputs and the input file's facts."""
    self_href = f"{base_url}/jobs/{job.id}"
    links = [{"href": self_href, "rel": "self", "type": "application/json",
              "title": "this document"}]
    if job.status is JobStatus.successful:
        links += [
            {"href": f"{self_href}/results", "rel":
             "http://www.opengis.net/def/rel/ogc/1.0/results", "type": "application/json",
             "title": "results"},
            {"href": f"{self_href}/results/cloud", "rel": "enclosure",
             "type": "application/vnd.laszip" if job.laz else "application/vnd.las",
             "title": "flagged cloud"},
            {"href": f"{self_href}/results/statistics", "rel": "describedby",
             "type": "application/json", "title": "statistics"},
        ]
    return {
        "type": "process",
        "jobID": job.id,
        "processID": job.process_id,
        "status": job.status.value,
        "message": job.message,
        "progress": job.progress,
        "created": job.created,
        "started": job.started,
        "finished": job.finished,
        "updated": job.finished or job.started or job.created,
        "inputs": job.inputs,
        "input_file": job.facts,
        "links": links,
    }
