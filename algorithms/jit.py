"""numba for the package's compiled kernels, with an on-disk cache that cannot go stale.

Kernel modules import ``njit`` and ``prange`` from here, so the cache folder is set before any
kernel is decorated. Detector modules import their kernel modules inside the functions that run
them, and modules without kernels (``temporal``, ``stats``) never import numba: its import and
first cached load cost about 0.3 s, a large share of a short command's run time.
"""

from __future__ import annotations

import os

import numba
from numba import njit, prange

from algorithms import source_digest

__all__ = ["NUMBA_CACHE_DIR", "njit", "prange"]


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
