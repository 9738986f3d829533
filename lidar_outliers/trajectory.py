"""Trajectory files: the scanner platform's path, as mobile-mapping systems deliver it.

Format (what ``lidar-outliers simulate`` writes beside the cloud, ``<name>.trajectory.txt``):
plain text, one sample per line, columns ``time x y z``:

* ``time`` in seconds, the same time base as the points' ``gps_time``; strictly increasing;
* ``x y z`` in metres, the same coordinate system as the cloud (file coordinates, not scaled
  integers), of the vehicle's reference point (the simulator's: an IMU on the roof; its truth
  file gives the scanners' lever arms from it);
* columns separated by spaces, tabs, commas or semicolons; further columns (roll, pitch,
  heading...) are ignored; lines starting with ``#`` and blank lines are skipped, and so is a
  first line of column names (``time,x,y,z``).

The scanners' lever arms are parameters of the ``transient`` detector (``lever_arms``), not part
of the file. Any problem gives a :class:`~.errors.ParameterError` with one line naming the
file and the line.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from lidar_outliers.errors import ParameterError

#: Largest trajectory file read (bytes): 200 Hz for 10 hours is about 300 MB of text.
MAX_TRAJECTORY_BYTES = 512 * 1024**2

_SPLIT = re.compile(r"[\s,;]+")


def read_trajectory(path: str | os.PathLike[str], name: str | None = None) -> np.ndarray:
    """(m, 4) float64 rows of time, x, y, z from a trajectory file (module docstring).

    ``name`` is how the file is called in messages (default: its file name).
    """
    path = Path(path)
    name = name or path.name
    try:
        size = path.stat().st_size
        if size > MAX_TRAJECTORY_BYTES:
            raise ParameterError(f"trajectory {name}: {size} bytes, more than the limit of "
                                 f"{MAX_TRAJECTORY_BYTES}")
        raw = path.read_bytes()
    except OSError as exc:
        raise ParameterError(f"cannot read trajectory {name}: {exc.strerror}") from None
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        raise ParameterError(f"trajectory {name}: not a text file (expected lines of "
                             f"'time x y z')") from None
    return parse_trajectory(text, name)


def parse_trajectory(text: str, name: str = "trajectory") -> np.ndarray:
    """(m, 4) float64 time, x, y, z from the text of a trajectory file."""
    rows: list[list[float]] = []
    lines: list[int] = []
    first = True
    for number, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        if not stripped or stripped.startswith("#"):
            continue
        fields = [f for f in _SPLIT.split(stripped) if f]
        if first and fields and not _is_number(fields[0]):
            first = False  # a line of column names
            continue
        first = False
        if len(fields) < 4:
            raise ParameterError(f"trajectory {name} line {number}: {len(fields)} columns, "
                                 f"expected time x y z")
        try:
            rows.append([float(f) for f in fields[:4]])
        except ValueError:
            raise ParameterError(f"trajectory {name} line {number}: not numbers: "
                                 f"{stripped[:60]!r}") from None
        lines.append(number)
    traj = np.asarray(rows, dtype=np.float64).reshape(-1, 4)
    return check_trajectory(traj, name, lines)


def check_trajectory(
    traj: np.ndarray, name: str = "trajectory", lines: list[int] | None = None
) -> np.ndarray:
    """``traj`` as (m, 4) float64 when it is a usable trajectory; ParameterError otherwise.

    ``lines``: the file line of each row, for the messages (default: row numbers from 1).
    """
    traj = np.asarray(traj, dtype=np.float64)
    if traj.ndim != 2 or traj.shape[1] != 4:
        raise ParameterError(f"trajectory {name}: shape {traj.shape}, expected rows of "
                             f"time x y z")
    if len(traj) < 2:
        raise ParameterError(f"trajectory {name}: {len(traj)} samples, at least two lines of "
                             f"'time x y z' are needed")
    where = lines or list(range(1, len(traj) + 1))
    bad = np.flatnonzero(~np.isfinite(traj).all(axis=1))
    if bad.size:
        raise ParameterError(f"trajectory {name} line {where[bad[0]]}: NaN or infinite value")
    back = np.flatnonzero(np.diff(traj[:, 0]) <= 0)
    if back.size:
        i = int(back[0]) + 1
        now, before = float(traj[i, 0]), float(traj[i - 1, 0])
        raise ParameterError(f"trajectory {name} line {where[i]}: time {now!r} does not "
                             f"increase (previous {before!r}); times must increase strictly")
    return traj


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def describe_trajectory(traj: np.ndarray, name: str) -> dict[str, object]:
    """JSON facts of a trajectory for the statistics."""
    return {"name": name, "samples": int(len(traj)),
            "time": [float(traj[0, 0]), float(traj[-1, 0])]}
