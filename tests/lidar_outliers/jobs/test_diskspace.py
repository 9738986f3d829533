"""A full disk recognised from real failed writes (/dev/full answers every write with ENOSPC),
and the room check against the real free space."""

from __future__ import annotations

import errno
import os
import shutil
from pathlib import Path

import pytest

from lidar_outliers.errors import LidarOutliersError
from lidar_outliers.jobs.diskspace import DiskFull, check_room, free_bytes, is_disk_full


def write_to_full_device() -> OSError:
    if not os.path.exists("/dev/full"):
        pytest.skip("no /dev/full on this system")
    try:
        with open("/dev/full", "wb") as out:
            out.write(b"x")
            out.flush()
    except OSError as exc:
        return exc
    raise AssertionError("writing to /dev/full succeeded")


def test_a_failed_write_is_recognised_also_when_wrapped() -> None:
    error = write_to_full_device()
    assert error.errno == errno.ENOSPC and is_disk_full(error)
    try:
        try:
            raise error
        except OSError as exc:
            raise LidarOutliersError("could not write the result") from exc
    except LidarOutliersError as wrapped:
        assert is_disk_full(wrapped)
    assert not is_disk_full(FileNotFoundError(errno.ENOENT, "missing"))
    assert not is_disk_full(ValueError("bad value"))


def test_room_check_counts_the_file_and_its_result(tmp_path: Path) -> None:
    free = shutil.disk_usage(tmp_path).free
    assert free_bytes(tmp_path / "not" / "yet") == pytest.approx(free, rel=0.01)
    check_room(tmp_path, 1000, 0)
    with pytest.raises(DiskFull, match="MIN_FREE_BYTES"):
        check_room(tmp_path, free // 2 + 2**20, 0)  # fits once, not twice
    check_room(tmp_path, free // 2 + 2**20, 0, received=True)  # already on the disk
    with pytest.raises(DiskFull):
        check_room(tmp_path, 0, free + 2**30)
