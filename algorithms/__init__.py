"""Pure numerical code of lidar-outliers: numpy arrays in, numpy arrays out.

No files, no web, no queue. Each detector is a function ``detect_<name>(xyz, ..., *, params)``
returning a :class:`algorithms.result.DetectorResult`.
"""

from __future__ import annotations

import hashlib
from pathlib import Path


def source_digest(folder: Path = Path(__file__).parent) -> str:
    """A digest of every module in ``folder`` (this package): the kernels' real dependencies."""
    sources = sorted(folder.glob("*.py"))
    digest = hashlib.sha256()
    for path in sources:
        digest.update(path.name.encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()[:16]
