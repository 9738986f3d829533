"""The names of a job's and an upload's objects in the storage (the API and the worker agree
here), and the local scratch folders a host works in.

With local storage the keys are paths under ``DATA_DIR``: ``jobs/<id>/input.las``,
``jobs/<id>/result.las``, ``jobs/<id>/statistics.json``, ``uploads/<user>/<id>.las`` ...
"""

from __future__ import annotations

import os
import shutil
import time
import uuid
from pathlib import Path

from lidar_outliers.jobs.settings import Settings

#: Objects of a finished job that a failed run must not leave behind.
RESULT_NAMES = ("result.las", "result.laz", "statistics.json")


def job_prefix(job_id: str) -> str:
    """Every object of the job starts with this (its folder with local storage)."""
    return f"jobs/{job_id}/"


def input_key(job_id: str, laz: bool) -> str:
    return job_prefix(job_id) + ("input.laz" if laz else "input.las")


def result_key(job_id: str, laz: bool) -> str:
    return job_prefix(job_id) + ("result.laz" if laz else "result.las")


def statistics_key(job_id: str) -> str:
    return job_prefix(job_id) + "statistics.json"


def trajectory_key(job_id: str) -> str:
    """The job's optional trajectory file (multipart part ``trajectory``)."""
    return job_prefix(job_id) + "trajectory.txt"


def tiles_prefix(job_id: str) -> str:
    """The tile files and the tiles' partial results of a job run over several workers."""
    return job_prefix(job_id) + "tiles/"


def tile_key(job_id: str, name: str) -> str:
    return tiles_prefix(job_id) + name


def derived_key(job_id: str, keep: str, laz: bool) -> str:
    """A download made from the result on first request (``?keep=``, ``?format=``)."""
    return job_prefix(job_id) + f"cloud-{keep}.{'laz' if laz else 'las'}"


def preview_key(job_id: str) -> str:
    return job_prefix(job_id) + "preview.png"


def view_points_key(job_id: str) -> str:
    """The viewer's decimated points of a job's result (made on first request)."""
    return job_prefix(job_id) + "view.points"


def upload_key(user_id: int, upload_id: str, suffix: str) -> str:
    return f"uploads/{user_id}/{upload_id}{suffix}"


def scratch(settings: Settings, label: str) -> Path:
    """A new, empty local folder of this process for one piece of work; the caller removes it
    (``shutil.rmtree``). Under DATA_DIR, so a local storage moves files in by renaming."""
    folder = settings.scratch_dir / f"{label}-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    folder.mkdir(parents=True)
    return folder


def sweep_scratch(settings: Settings, older_than: float) -> None:
    """Remove scratch folders left by processes that were killed (older than any job may run:
    nothing still uses them)."""
    if not settings.scratch_dir.is_dir():
        return
    cutoff = time.time() - older_than
    for folder in settings.scratch_dir.iterdir():
        try:
            if folder.stat().st_mtime < cutoff:
                shutil.rmtree(folder, ignore_errors=True)
        except FileNotFoundError:
            pass
