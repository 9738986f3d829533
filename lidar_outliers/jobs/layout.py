"""Where a job's files live under ``DATA_DIR/jobs/<id>/`` (the API and the worker agree here)."""

from __future__ import annotations

from pathlib import Path

from lidar_outliers.jobs.settings import Settings

#: Files of a finished job that a failed run must not leave behind.
RESULT_NAMES = ("result.las", "result.laz", "statistics.json")


def job_dir(settings: Settings, job_id: str) -> Path:
    return settings.jobs_dir / job_id


def input_path(settings: Settings, job_id: str, laz: bool) -> Path:
    return job_dir(settings, job_id) / ("input.laz" if laz else "input.las")


def result_path(settings: Settings, job_id: str, laz: bool) -> Path:
    return job_dir(settings, job_id) / ("result.laz" if laz else "result.las")


def statistics_path(settings: Settings, job_id: str) -> Path:
    return job_dir(settings, job_id) / "statistics.json"


def trajectory_path(settings: Settings, job_id: str) -> Path:
    """The job's optional trajectory file (multipart part ``trajectory``)."""
    return job_dir(settings, job_id) / "trajectory.txt"


def folder_bytes(folder: Path) -> int:
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())
