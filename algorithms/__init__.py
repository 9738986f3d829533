"""Pure numerical code of lidar-outliers: numpy arrays in, numpy arrays out.

No files, no web, no queue. Each detector is a function ``detect_<name>(xyz, ..., *, params)``
returning a :class:`algorithms.result.DetectorResult`.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import numba


def source_digest(folder: Path = Path(__file__).parent) -> str:
    """A digest of every module in ``folder`` (this package): the kernels' real dependencies."""
    sources = sorted(folder.glob("*.py"))
    digest = hashlib.sha256()
    for path in sources:
        digest.update(path.name.encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()[:16]


def _cache_dir() -> str | None:
    """Where numba keeps this package's compiled kernels: one folder per source digest.

    numba's on-disk cache checks only the file of the function it compiled, not the kernels it
    inlined from other modules: after an edit or an upgrade of ``quadric.py``, a cached
    ``section.py`` kernel would go on running the old fit. A folder per digest of all the
    package's sources cannot be stale. It lies under NUMBA_CACHE_DIR when that is set, else
    under the user's cache folder; None (numba's default) when neither can be written.
    """
    base = numba.config.CACHE_DIR or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache"),
        "lidar-outliers",
    )
    folder = os.path.join(base, f"numba-{source_digest()}")
    try:
        os.makedirs(folder, exist_ok=True)
    except OSError:
        return None
    return folder if os.access(folder, os.W_OK) else None


#: The folder of this package's numba cache (set before any kernel module is imported).
NUMBA_CACHE_DIR = _cache_dir()
if NUMBA_CACHE_DIR is not None:
    numba.config.CACHE_DIR = NUMBA_CACHE_DIR
