"""The JSON documents of OGC API - Processes about one job, shared by the API (which answers
them) and the worker (which posts them to a job's subscriber): the status document
(``statusInfo``) and the results document (``results``, outputs by reference)."""

from __future__ import annotations

from typing import Any

from lidar_outliers import view
from lidar_outliers.jobs.store import Job, JobStatus

OGC_REL = "http://www.opengis.net/def/rel/ogc/1.0/"
MEDIA = {".las": "application/vnd.las", ".laz": "application/vnd.laszip"}


def cloud_type(job: Job) -> str:
    return MEDIA[".laz" if job.laz else ".las"]


def status_document(job: Job, base_url: str = "") -> dict[str, Any]:
    """OGC API - Processes statusInfo plus the resolved inputs and the input file's facts.
    ``base_url``: prefix of the links (empty: links relative to the API's root)."""
    self_href = f"{base_url}/jobs/{job.id}"
    links = [{"href": self_href, "rel": "self", "type": "application/json",
              "title": "this document"},
             {"href": f"{self_href}?f=html", "rel": "alternate", "type": "text/html",
              "title": "this document as HTML"}]
    if job.status is JobStatus.successful:
        links += [
            {"href": f"{self_href}/results", "rel": OGC_REL + "results",
             "type": "application/json", "title": "results"},
            {"href": f"{self_href}/results/cloud", "rel": "enclosure",
             "type": cloud_type(job), "title": "flagged cloud"},
            {"href": f"{self_href}/results/statistics", "rel": "describedby",
             "type": "application/json", "title": "statistics"},
        ]
    document: dict[str, Any] = {
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
    # the standard's times are strings: a time not reached yet is left out, not null
    return {k: v for k, v in document.items() if v is not None or k not in ("started", "finished")}


def results_document(job: Job, base_url: str = "") -> dict[str, Any]:
    """The outputs of a successful job, by reference (links with href and media type)."""
    base = f"{base_url}/jobs/{job.id}/results"
    return {
        "cloud": {"href": f"{base}/cloud", "type": cloud_type(job),
                  "title": "flagged cloud (?keep=inliers|outliers, ?format=las|laz)"},
        "statistics": {"href": f"{base}/statistics", "type": "application/json"},
        "preview": {"href": f"{base}/preview", "type": "image/png"},
        "points": {"href": f"{base}/points", "type": view.MEDIA_TYPE,
                   "title": "decimated points for a viewer (?max_points=N)"},
    }
