"""Per-point columns in memory-mapped files, kept out of the process's resident set.

A tiled run keeps its whole-file columns (coordinates, times, flags, scores, a pre-pass's
facts) in ``.npy`` files mapped into memory. Every page a process reads or writes through a
map stays in its resident set until the map is closed: a pass over 50 M points of 60 bytes
each left 2.8 GB of file pages resident in the worker that ran it. The pages are the page
cache's (the maps are shared: written pages reach the file whether or not they stay mapped),
so a pass can give them back as it goes with ``madvise(MADV_DONTNEED)`` and fault them in
again, cheaply, from the cache when they are read again. Resident memory then follows the
chunk a pass works on, not the file.
"""

from __future__ import annotations

import mmap
from collections.abc import Iterable, Iterator
from typing import Any

import numpy as np

#: Points a pass reads or writes through its maps between two releases of their pages.
RELEASE_POINTS = 2_000_000


def _shared_mapping(arr: Any) -> mmap.mmap | None:
    """The shared map under ``arr`` (a ``numpy.memmap`` or a view of one), else None. A
    copy-on-write map (mode ``c``) holds its changes in its own pages: those are not given
    back."""
    base = arr
    while base is not None:
        if isinstance(base, np.memmap) and base.mode == "c":
            return None
        if isinstance(base, mmap.mmap):
            return base
        base = getattr(base, "base", None)
    return None


def release(*arrays: Any) -> None:
    """Drop the pages of the memory-mapped ``arrays`` from this process's resident set (their
    content stays in the file and the page cache); other arrays are left as they are."""
    if not hasattr(mmap, "MADV_DONTNEED"):
        return
    done: set[int] = set()
    for arr in arrays:
        mapping = _shared_mapping(arr)
        if mapping is not None and not mapping.closed and id(mapping) not in done:
            done.add(id(mapping))
            mapping.madvise(mmap.MADV_DONTNEED)


def filled(arr: np.ndarray, value: Any) -> None:
    """Every element of ``arr`` set to ``value``, a chunk at a time, the chunk's pages given
    back after it (when ``arr`` is a map)."""
    for a in range(0, len(arr), RELEASE_POINTS):
        arr[a:a + RELEASE_POINTS] = value
        release(arr)


def gathered(arr: np.ndarray, rows: np.ndarray, every: int = RELEASE_POINTS) -> np.ndarray:
    """``arr[rows]`` for sorted ``rows``, read a span of ``every`` positions at a time, each
    span's pages given back after it: rows spread over a whole file touch every page of it."""
    out = np.empty((len(rows), *arr.shape[1:]), dtype=arr.dtype)
    for lo, hi in _spans(rows, len(arr), every):
        out[lo:hi] = arr[rows[lo:hi]]
        release(arr)
    return out


def scattered(arr: np.ndarray, rows: np.ndarray, values: np.ndarray,
              every: int = RELEASE_POINTS) -> None:
    """``arr[rows] = values`` for sorted ``rows``, a span of ``every`` positions at a time, each
    span's pages given back after it."""
    for lo, hi in _spans(rows, len(arr), every):
        arr[rows[lo:hi]] = values[lo:hi]
        release(arr)


def _spans(rows: np.ndarray, n: int, every: int) -> list[tuple[int, int]]:
    """(lo, hi) per span of ``every`` positions of an array of n: the part rows[lo:hi] of the
    sorted ``rows`` that falls in it (empty spans left out)."""
    cuts = np.searchsorted(rows, np.r_[np.arange(0, max(n, 1), every), max(n, 1)])
    return [(int(a), int(b)) for a, b in zip(cuts[:-1], cuts[1:], strict=True) if b > a]


class Releaser:
    """Releases the pages of ``arrays`` after every ``every`` points a pass has moved through
    them (:meth:`moved`), and at :meth:`now`."""

    def __init__(self, arrays: Iterable[Any], every: int = RELEASE_POINTS) -> None:
        self.arrays = list(arrays)
        self.every = every
        self.pending = 0

    def add(self, *arrays: Any) -> None:
        """Watch more arrays (made while the pass runs)."""
        self.arrays.extend(arrays)

    def moved(self, points: int) -> None:
        """Count ``points`` read or written; release when ``every`` have been since the last."""
        self.pending += points
        if self.pending >= self.every:
            self.now()

    def now(self) -> None:
        """Release every watched array's pages."""
        release(*self.arrays)
        self.pending = 0


def releasing(results: Iterable[dict[str, Any]], releaser: Releaser
              ) -> Iterator[dict[str, Any]]:
    """The tiles' results as they come; after each, its points (``index``) count as moved
    through the releaser's arrays."""
    for res in results:
        yield res
        releaser.moved(len(res["index"]))
    releaser.now()
