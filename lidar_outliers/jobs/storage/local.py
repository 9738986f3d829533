"""Objects as files under a root folder (``DATA_DIR``): the key is the relative path.

Puts write under a temporary name and rename into place; a moved file on the same file system
is only renamed, and copies are hard links where the file system allows (objects are never
changed in place, so sharing an inode is safe).
"""

from __future__ import annotations

import contextlib
import os
import shutil
from collections.abc import Iterator
from pathlib import Path

from lidar_outliers.atomic import atomic_path
from lidar_outliers.jobs.storage import (
    CHUNK_BYTES,
    ObjectInfo,
    ObjectMissing,
    Storage,
    StorageError,
    check_key,
)


class LocalStorage(Storage):
    def __init__(self, root: Path) -> None:
        self.root = Path(root)

    def path(self, key: str) -> Path:
        return self.root / check_key(key)

    def put_file(self, key: str, path: Path, *, move: bool = False) -> int:
        target = self.path(key)
        size = path.stat().st_size
        with atomic_path(target) as tmp:
            if move:
                try:
                    os.replace(path, tmp)
                    return size
                except OSError:  # another file system: copy, then drop the source
                    pass
            _link_or_copy(path, tmp)
        if move:
            path.unlink(missing_ok=True)
        return size

    def copy(self, source: str, target: str) -> int:
        src = self.path(source)
        if not src.is_file():
            raise ObjectMissing(source)
        with atomic_path(self.path(target)) as tmp:
            _link_or_copy(src, tmp)
        return src.stat().st_size

    def get_file(self, key: str, path: Path) -> int:
        src = self.path(key)
        if not src.is_file():
            raise ObjectMissing(key)
        with atomic_path(path) as tmp:
            _link_or_copy(src, tmp)
        return path.stat().st_size

    def iter_range(self, key: str, start: int = 0, end: int | None = None,
                   chunk_bytes: int = CHUNK_BYTES) -> Iterator[bytes]:
        try:
            handle = open(self.path(key), "rb")  # noqa: SIM115 - closed by the generator
        except FileNotFoundError:
            raise ObjectMissing(key) from None
        return _read_range(handle, start, end, chunk_bytes)

    def info(self, key: str) -> ObjectInfo | None:
        try:
            st = self.path(key).stat()
        except FileNotFoundError:
            return None
        return ObjectInfo(size=st.st_size, etag=f'"{st.st_ino:x}-{st.st_size:x}-'
                          f'{st.st_mtime_ns:x}"', modified=st.st_mtime)

    def delete(self, key: str) -> None:
        self.path(key).unlink(missing_ok=True)

    def delete_prefix(self, prefix: str) -> None:
        folder = self.path(prefix.rstrip("/"))
        if folder.is_dir():
            shutil.rmtree(folder, ignore_errors=True)
        else:
            folder.unlink(missing_ok=True)

    def prefix_bytes(self, prefix: str) -> int:
        folder = self.path(prefix.rstrip("/"))
        if not folder.is_dir():
            return 0
        total = 0
        for p in folder.rglob("*"):
            with contextlib.suppress(FileNotFoundError):
                if p.is_file():
                    total += p.stat().st_size
        return total

    def check(self) -> None:
        try:
            self.root.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise StorageError(f"cannot use {self.root}: {exc}") from None
        if not os.access(self.root, os.W_OK):
            raise StorageError(f"{self.root} is not writable")

    def describe(self) -> str:
        return str(self.root)


def _link_or_copy(source: Path, target: Path) -> None:
    try:
        os.link(source, target)
    except OSError:
        shutil.copyfile(source, target)


def _read_range(handle, start: int, end: int | None, chunk_bytes: int) -> Iterator[bytes]:
    with handle:
        handle.seek(start)
        left = None if end is None else end - start + 1
        while left is None or left > 0:
            chunk = handle.read(chunk_bytes if left is None else min(chunk_bytes, left))
            if not chunk:
                return
            if left is not None:
                left -= len(chunk)
            yield chunk
