"""A full disk as an ordinary error: recognising it, and keeping room before accepting a file.

The API refuses a file up front unless ``DATA_DIR``'s disk keeps ``MIN_FREE_BYTES`` free after
the file *and* room for its result (about as large again), so the database, the Redis
append-only file and the running jobs are not the ones to hit the wall. When the disk fills
anyway (another process, a file sent without a declared length), the failed write is recognised
here, its partial file removed by the caller, and the client told so (507).
"""

from __future__ import annotations

import errno
import shutil
from pathlib import Path

from lidar_outliers.errors import LidarOutliersError

#: errno values of a write that found no room (ENOSPC; EDQUOT: the user's disk quota).
FULL_ERRNOS = {errno.ENOSPC, errno.EDQUOT}
#: How databases word it: SQLite ("database or disk is full"), PostgreSQL ("could not extend
#: file ...: No space left on device"; SQLSTATE 53100 disk_full).
FULL_MESSAGES = ("database or disk is full", "no space left on device", "disk full")


class DiskFull(LidarOutliersError):
    """No room on the disk of ``DATA_DIR`` (now, or after the file being accepted)."""


def is_disk_full(exc: BaseException | None) -> bool:
    """Whether ``exc`` or anything it was raised from is a write that found the disk full."""
    seen: set[int] = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        if isinstance(exc, DiskFull):
            return True
        if isinstance(exc, OSError) and exc.errno in FULL_ERRNOS:
            return True
        if any(m in str(exc).lower() for m in FULL_MESSAGES):
            return True
        exc = exc.__cause__ or exc.__context__ or getattr(exc, "orig", None)
    return False


def free_bytes(path: Path) -> int:
    """Free bytes (for an unprivileged user) on the file system holding ``path``; the nearest
    existing parent is asked when ``path`` does not exist yet."""
    path = Path(path)
    while not path.exists() and path != path.parent:
        path = path.parent
    return shutil.disk_usage(path).free


def check_room(folder: Path, incoming: int, min_free: int, *, received: bool = False) -> None:
    """Raise :class:`DiskFull` unless ``folder``'s disk has room for ``incoming`` bytes and a
    result as large, with ``min_free`` bytes to spare. ``received``: the file is on the disk
    already (only its result is still to come)."""
    free = free_bytes(folder)
    needed = (1 if received else 2) * incoming + min_free
    if free < needed:
        what = ""
        if incoming:
            what = "the result of a file" if received else "a file and its result"
            what = f"{what} of {incoming} bytes need "
        raise DiskFull(f"the server's disk is full: {free} bytes free, {what}"
                       f"{needed} bytes with the {min_free} bytes kept free (MIN_FREE_BYTES)")
