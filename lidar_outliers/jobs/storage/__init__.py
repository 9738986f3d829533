"""Where uploads, job inputs and results are kept: one small interface, two siblings.

- :class:`~lidar_outliers.jobs.storage.local.LocalStorage`: files under ``DATA_DIR`` (the
  default; one host, or hosts sharing that folder);
- :class:`~lidar_outliers.jobs.storage.s3.S3Storage`: an S3-compatible object store
  (``STORAGE_URL=s3://bucket/prefix``), for API and worker hosts that share nothing else.

Objects are named by keys such as ``jobs/<id>/result.las`` (:mod:`lidar_outliers.jobs.layout`).
Every put is whole or nothing: a reader never sees half an object. The API and the worker use
this interface only; a worker copies a job's input to a local scratch folder, runs it, and puts
the result back.
"""

from __future__ import annotations

import abc
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from lidar_outliers.errors import LidarOutliersError
from lidar_outliers.jobs.settings import Settings

#: Bytes per chunk when streaming an object.
CHUNK_BYTES = 1024**2


class StorageError(LidarOutliersError):
    """The object storage failed or cannot be reached."""


class ObjectMissing(StorageError):
    """No object under the key."""

    def __init__(self, key: str) -> None:
        super().__init__(f"no object {key!r}")
        self.key = key


@dataclass(frozen=True)
class ObjectInfo:
    size: int
    #: A strong validator of the content (quoted, as HTTP's ETag).
    etag: str
    #: Seconds since the epoch of the last change.
    modified: float


def check_key(key: str) -> str:
    """Keys are relative POSIX paths without empty, ``.`` or ``..`` parts."""
    parts = key.split("/")
    if not key or key.startswith("/") or any(p in ("", ".", "..") for p in parts):
        raise ValueError(f"not a storage key: {key!r}")
    return key


class Storage(abc.ABC):
    """Objects under keys. Implementations are safe to share between threads."""

    @abc.abstractmethod
    def put_file(self, key: str, path: Path, *, move: bool = False) -> int:
        """Store the file at ``path`` under ``key`` (replacing any object there); return its
        size. ``move``: the local file is no longer needed (it may be renamed into place)."""

    @abc.abstractmethod
    def copy(self, source: str, target: str) -> int:
        """Store a copy of object ``source`` under ``target``; return its size."""

    @abc.abstractmethod
    def get_file(self, key: str, path: Path) -> int:
        """Write the object to the local file ``path`` (whole or not at all); return its size.
        Raises :class:`ObjectMissing`."""

    @abc.abstractmethod
    def iter_range(self, key: str, start: int = 0, end: int | None = None,
                   chunk_bytes: int = CHUNK_BYTES) -> Iterator[bytes]:
        """The object's bytes ``start`` to ``end`` inclusive (to its end when None), in
        chunks. Raises :class:`ObjectMissing` before the first chunk."""

    @abc.abstractmethod
    def info(self, key: str) -> ObjectInfo | None:
        """Size and validators of the object, or None when there is none."""

    @abc.abstractmethod
    def delete(self, key: str) -> None:
        """Remove the object if it exists."""

    @abc.abstractmethod
    def delete_prefix(self, prefix: str) -> None:
        """Remove every object whose key starts with ``prefix`` (a folder such as
        ``jobs/<id>/``)."""

    @abc.abstractmethod
    def prefix_bytes(self, prefix: str) -> int:
        """Total size of the objects whose keys start with ``prefix``."""

    @abc.abstractmethod
    def check(self) -> None:
        """Raise :class:`StorageError` unless the storage can be used (for /health)."""

    @abc.abstractmethod
    def describe(self) -> str:
        """Where the objects are, for messages."""

    def size(self, key: str) -> int | None:
        found = self.info(key)
        return found.size if found else None

    def exists(self, key: str) -> bool:
        return self.info(key) is not None

    def read_bytes(self, key: str) -> bytes:
        return b"".join(self.iter_range(key))


def open_storage(settings: Settings) -> Storage:
    """The storage the settings name: S3 for ``STORAGE_URL=s3://...``, else ``DATA_DIR``."""
    if settings.storage_url:
        from lidar_outliers.jobs.storage.s3 import S3Storage

        return S3Storage.from_url(settings.storage_url, settings.s3_endpoint_url or None)
    from lidar_outliers.jobs.storage.local import LocalStorage

    return LocalStorage(settings.data_dir)
