"""Pure numerical code of lidar-outliers: numpy arrays in, numpy arrays out.

No files, no web, no queue. Each detector is a function ``detect_<name>(xyz, ..., *, params)``
returning a :class:`algorithms.result.DetectorResult`.

Importing a detector module is light: it declares its parameters and its detect function and
imports numba kernels (from a module of its steps) and scipy inside the functions that use them,
so that reading the parameters does not pay for numba's and scipy's start-up.
"""

from __future__ import annotations

import hashlib
from pathlib import Path


def source_digest(folder: Path = Path(__file__).parent) -> str:
    """A digest of every module under ``folder`` (this package, subpackages included): the
    kernels' real dependencies."""
    digest = hashlib.sha256()
    for path in sorted(folder.rglob("*.py")):
        digest.update(path.relative_to(folder).as_posix().encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()[:16]
