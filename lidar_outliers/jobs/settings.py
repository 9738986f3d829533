"""All configuration of the service, the worker, `serve` and `users`, from the environment.

Every field is read from the environment variable of the same name in upper case (``DATA_DIR``,
``REDIS_URL``, ...). With nothing set, the defaults are those of ``make run`` on one machine.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import Literal

from pydantic import Field, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

PROJECT_ROOT = Path(__file__).resolve().parents[2]
GIB = 1024**3


class Settings(BaseSettings):
    """Service settings; see the README's table of environment variables."""

    model_config = SettingsConfigDict(env_prefix="", case_sensitive=False, extra="ignore")

    environment: Literal["dev", "prod"] = Field(
        "dev", description="`prod`: no development key, no exception text in answers, "
        "REDIS_URL and DATA_DIR must be set."
    )
    redis_url: str = Field(
        "redis://127.0.0.1:6379/0",
        description="Celery broker. `lidar-outliers serve` starts its own redis-server when unset.",
    )
    data_dir: Path = Field(
        PROJECT_ROOT / "data",
        description="Uploads and results (unless STORAGE_URL is set), the SQLite database "
        "(unless DATABASE_URL is set), scratch space of this host, the local Redis AOF.",
    )
    database_url: str = Field(
        "",
        description="SQLAlchemy URL of the job and key database, e.g. "
        "postgresql://user:password@host/db; empty: SQLite file DATA_DIR/service.sqlite3.",
    )
    storage_url: str = Field(
        "",
        description="s3://bucket/prefix keeps uploads, inputs and results in S3-compatible "
        "object storage (credentials from the AWS environment variables); empty: DATA_DIR.",
    )
    s3_endpoint_url: str = Field(
        "", description="Endpoint of an S3-compatible store (MinIO ...); empty: AWS S3."
    )
    max_upload_bytes: int = Field(2 * GIB, gt=0, description="Largest accepted upload (413 above).")
    max_active_jobs_per_user: int = Field(
        4, ge=1, description="Queued + running jobs per user (429 with Retry-After above)."
    )
    max_stored_bytes_per_user: int = Field(
        20 * GIB, gt=0, description="Uploads + inputs + results kept per user (413 above)."
    )
    retention_days: float = Field(
        7.0, gt=0, description="Finished jobs and unused uploads older than this are deleted."
    )
    resumable_expiry_hours: float = Field(
        24.0, gt=0, description="An unfinished resumable (tus) upload is deleted this long after "
        "its last PATCH, and its reserved bytes freed."
    )
    cleanup_interval_seconds: float = Field(
        3600.0, gt=0, description="How often the API runs the retention cleanup."
    )
    task_time_limit: int = Field(
        6 * 3600, gt=0, description="Hard time limit of one job in seconds (the worker is killed)."
    )
    visibility_timeout: int = Field(
        0, ge=0, description="Seconds after which Redis re-delivers a job whose worker vanished "
        "(whole machine or worker process killed); must exceed TASK_TIME_LIMIT; 0 = "
        "TASK_TIME_LIMIT + 600.",
    )
    max_attempts: int = Field(
        2, ge=1, description="Deliveries of a job whose worker died before it is marked failed."
    )
    heartbeat_interval_seconds: float = Field(
        10.0, gt=0, description="How often a worker records that its running jobs are alive, "
        "and looks for jobs of vanished workers."
    )
    stale_job_seconds: float = Field(
        60.0, gt=0, description="A running job without a heartbeat for this long (or whose "
        "worker process on this host is gone) is re-queued, or failed after MAX_ATTEMPTS."
    )
    worker_concurrency: int = Field(1, ge=1, description="Worker processes `serve` starts.")
    tile_job_points: int = Field(
        2_000_000, ge=1, description="A job of more points is cut into tiles that every "
        "worker takes part in (when its pipeline runs in tiles).")
    tile_size: float = Field(
        0.0, ge=0, description="Edge in metres of the tiles of such a job; 0 = chosen from the "
        "file's density (about 600 k points a tile).")
    api_host: str = Field("127.0.0.1", description="Address `serve` binds the API to.")
    api_port: int = Field(8000, ge=1, le=65535, description="Port `serve` binds the API to.")
    retry_after_seconds: int = Field(30, ge=1, description="Retry-After sent with 429.")
    cors_origins: str = Field(
        "", description="Comma-separated origins (https://portal.example) whose browser "
        "scripts may call the API; empty: none."
    )
    callback_allow: str = Field(
        "", description="Comma-separated host names that subscriber callbacks may reach even "
        "though they resolve to private, loopback, link-local or reserved addresses."
    )
    sync_max_points: int = Field(
        2_000_000, ge=0, description="Largest cloud (points) run synchronously with "
        "`Prefer: wait`; larger ones run asynchronously."
    )
    sync_wait_seconds: float = Field(
        120.0, gt=0, description="How long a synchronous execution waits for its job before "
        "answering asynchronously."
    )
    health_interval_seconds: float = Field(
        5.0, gt=0, description="How often the API checks Redis, the workers, the database and "
        "the storage for /health (answers use the last check)."
    )
    min_free_bytes: int = Field(
        256 * 1024**2, ge=0, description="Free space kept on DATA_DIR's disk: an upload is "
        "refused with 507 unless the disk keeps this much after the file and room for its "
        "result (as large again); a worker fails a job cleanly when the disk fills."
    )
    api_workers: int = Field(
        2, ge=1, description="API processes (uvicorn workers) `serve` starts."
    )

    @model_validator(mode="after")
    def _resolve(self) -> Settings:
        if self.environment == "prod":
            missing = {"redis_url", "data_dir"} - self.model_fields_set
            if missing:  # defaults meant for one developer's machine
                names = ", ".join(sorted(m.upper() for m in missing))
                raise ValueError(f"ENVIRONMENT=prod needs {names} set explicitly")
        self.data_dir = self.data_dir.expanduser().resolve()
        if not self.database_url:
            self.database_url = f"sqlite:///{self.data_dir / 'service.sqlite3'}"
        if self.storage_url:
            scheme, _, rest = self.storage_url.partition("://")
            if scheme != "s3" or not rest.split("/", 1)[0]:
                raise ValueError(
                    f"STORAGE_URL must look like s3://bucket/prefix, got {self.storage_url!r}"
                )
        if self.stale_job_seconds <= 2 * self.heartbeat_interval_seconds:
            # one late heartbeat must not make a live job look abandoned
            raise ValueError(
                f"STALE_JOB_SECONDS ({self.stale_job_seconds}) must exceed twice "
                f"HEARTBEAT_INTERVAL_SECONDS ({self.heartbeat_interval_seconds})"
            )
        if self.visibility_timeout == 0:
            self.visibility_timeout = self.task_time_limit + 600
        if self.visibility_timeout <= self.task_time_limit:
            # a job still running would be delivered a second time
            raise ValueError(
                f"VISIBILITY_TIMEOUT ({self.visibility_timeout}) must exceed TASK_TIME_LIMIT "
                f"({self.task_time_limit})"
            )
        return self

    @property
    def cors_origin_list(self) -> list[str]:
        return _split(self.cors_origins)

    @property
    def callback_allow_list(self) -> list[str]:
        return [h.lower().rstrip(".") for h in _split(self.callback_allow)]

    @property
    def soft_time_limit(self) -> int:
        """The job gets SoftTimeLimitExceeded (and fails cleanly) this long before the kill."""
        return max(1, self.task_time_limit - min(30, self.task_time_limit // 10))

    @property
    def db_path(self) -> Path:
        """The embedded SQLite database (used when DATABASE_URL is not set)."""
        return self.data_dir / "service.sqlite3"

    @property
    def incoming_dir(self) -> Path:
        """Request bodies being received by the API on this host, before they are checked."""
        return self.data_dir / "uploads" / "incoming"

    @property
    def resumable_dir(self) -> Path:
        """The bytes of resumable uploads received so far by the API on this host."""
        return self.data_dir / "uploads" / "resumable"

    @property
    def scratch_dir(self) -> Path:
        """Local working copies of this host: a job's input and result while a worker runs it,
        a result while the API derives another format or a preview from it."""
        return self.data_dir / "scratch"


def _split(text: str) -> list[str]:
    return [part.strip() for part in text.split(",") if part.strip()]


@lru_cache
def get_settings() -> Settings:
    """The process-wide settings (read once from the environment)."""
    return Settings()
